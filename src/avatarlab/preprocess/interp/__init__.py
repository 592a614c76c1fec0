"""Frame interpolation (seed 002, section 4.3): an XVFI-style network and a classical optical-flow baseline."""
