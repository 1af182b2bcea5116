"""The open world: when no effect of the library explains a measurement, find the missing term.

:mod:`.force` estimates a missing generalized force at a place of the rig from the residual of the
calibrated model, through the sensitivity of the measured channels to a force there, and scores the
place by its evidence.
"""
