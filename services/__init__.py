"""Brain-guided RL platform: services for simulation, EEG, learning and the web API."""
