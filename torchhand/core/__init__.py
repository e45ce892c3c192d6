"""Layer 0: what every other layer uses: input validation (:mod:`torchhand.core.check`)."""
