"""Integrators: one module per rendering method, each registering itself."""
