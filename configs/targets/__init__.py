"""Target definitions shipped with edgecal."""
