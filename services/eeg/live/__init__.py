"""Live EEG streams: ingest with integrity checks, LSL inlets, outlets and replay, and live
recordings written to disk as they come."""
