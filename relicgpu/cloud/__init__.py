"""Point clouds: meshing a scan into a closed solid, and the per-point geometry of clouds matched on their points."""
