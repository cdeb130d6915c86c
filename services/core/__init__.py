"""Shared, dependency-light building blocks: settings, schemas and constants.

Every other service may import ``services.core``; ``services.core`` imports no other service.
"""
