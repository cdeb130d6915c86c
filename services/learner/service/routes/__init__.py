"""HTTP routes of the learner service, one module per resource."""
