"""Simulation beside MJX: the native C-MuJoCo backend, the backend chooser and fixed-parameter walks."""
