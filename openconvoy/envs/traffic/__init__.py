"""highway-env roads, IDM/MOBIL traffic, and ``TrafficConvoyEnv``."""
