"""Performance benchmarks run by ``bgrl bench``; each writes JSON with ratios to a peer."""
