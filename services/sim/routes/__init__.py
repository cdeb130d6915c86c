"""HTTP and websocket routes of the sim service, one module per resource."""
