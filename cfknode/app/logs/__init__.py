"""Flight logs: MCAP with JSON messages; the writer, the format, the streaming reader."""
