"""The learner service: online human-feedback (HF) training sessions over HTTP (port 8003)."""
