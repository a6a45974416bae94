"""REST API over the campaign store and the model registry."""
