"""A released benchmark: ``export`` / ``import`` bundles, ``score`` a predictions file, ``publish`` a page."""
