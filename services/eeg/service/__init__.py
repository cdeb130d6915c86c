"""The EEG service (FastAPI, port 8002): settings, stores, calibration jobs, the live session
that decodes each action marker, the service state and routes."""
