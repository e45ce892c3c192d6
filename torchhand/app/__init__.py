"""Layer 9: the ``torchhand`` command line, the demo, and the runner that reads sequence
folders, drives the tracker and writes its outputs. Nothing in the library imports it."""
