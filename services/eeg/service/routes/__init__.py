"""HTTP and websocket routes of the EEG service, one module per resource."""
