"""The application: CLI, YAML config to settings, mission wiring, backends, logs, terminal UI, benchmarks."""
