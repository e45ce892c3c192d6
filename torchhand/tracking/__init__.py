"""Layer 7: the RGB-D tracker (thesis Ch. 4): depth preprocessing, the energy terms
(:mod:`torchhand.tracking.energies`) and Algorithm 1 (:mod:`torchhand.tracking.tracker`).
Frames in, results out: reading and writing sequence folders is the app layer's job."""
