"""Tuning science shared by auto-tune, frequency response and what-if gains.

``plants`` holds the plant models (device units and their linear form), ``identify``
the fits, ``devices`` each device's controller law, excitation and limits behind one
small interface (``DeviceLaw``), ``loops`` the laws as discrete transfer functions
around a linear plant with margins and predictions, ``frf`` the measured frequency
responses. Layering: numpy/scipy/python-control and the codecs' constants only; no
imports from the auto-tune, drivers, hub or api (tests/test_tuning_core.py checks).
"""
