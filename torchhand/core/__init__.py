"""Layer 0: what every other layer uses: input validation (:mod:`torchhand.core.check`)
and the errors a user can fix (:mod:`torchhand.core.errors`)."""
