"""Request and response schemas of the api, one module per resource (Create/Update/Public)."""
