"""Layer 1: generic batched solvers and robust losses, independent of hands and images.

- :mod:`torchhand.optim.levenberg_marquardt`: batched Levenberg-Marquardt with box bounds.
"""
