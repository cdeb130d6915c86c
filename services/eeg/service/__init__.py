"""The EEG service (FastAPI, port 8002): settings, stores, calibration jobs, live state and
routes."""
