"""YAML defaults shipped with edgecal (detector thresholds, targets, rigs, the daemon)."""
