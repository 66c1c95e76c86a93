"""Foxglove's standard schemas in the flight log, and a live view over a local WebSocket."""
