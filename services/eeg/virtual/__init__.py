"""The virtual subject: synthetic ErrP EEG offline, as a live source, over LSL and pushed to
the service's ingest websocket."""
