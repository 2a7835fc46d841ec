"""edgecal's test suite: a package, so the shared helper modules are imported package-relative."""
