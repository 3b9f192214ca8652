"""cpgjax: online-optimized Central Pattern Generator controllers for the Unitree Go1 in JAX."""

__version__ = "0.1.0"
