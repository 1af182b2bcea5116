"""The open world: when no effect of the library explains a measurement, find the missing term.

:mod:`.linear` gives the rig's response to a force at any place (the model linearized about its
motion); :mod:`.force` estimates the force history at a place from the residual of the model it starts from,
with its evidence; :mod:`.forms` is the catalogue of parametric terms (one file each); :mod:`.search`
ranks every form at the places where the force acts by evidence; :mod:`.effect_file` writes a candidate
out as an effect file that a study adds like any user's effect; :mod:`.verify` fits the leading candidates
on the full simulator inside a diagnosis and reports what was found.
"""
