"""Stage 1: EEG ingest, preprocessing, the EEGNet ErrP classifier and the virtual subject."""
