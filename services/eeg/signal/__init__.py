"""Causal signal processing shared by calibration and live decoding: filters, resampling,
band-pass and the epoch ring buffer."""
