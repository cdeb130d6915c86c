"""Celery workers that run the platform's jobs (guided PPO, reproductions, EEG calibration)."""
