"""OpenConvoy: cooperative driving in simulation and on real vehicles."""

__version__ = "0.1.0"
