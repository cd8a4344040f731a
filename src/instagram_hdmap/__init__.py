"""InstaGraM: instance-level graph modeling for vectorized HD map learning."""

__version__ = "0.1.0"
