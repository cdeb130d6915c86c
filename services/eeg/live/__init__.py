"""Live EEG: ingest with integrity checks, LSL inlets and replay, live recordings and the
live session that decodes each action marker."""
