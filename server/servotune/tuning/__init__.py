"""Tuning science shared by auto-tune, frequency response and what-if gains.

``plants`` holds the plant models (device units and their linear form), ``identify``
the fits, ``law`` the small interface (``DeviceLaw``) behind which each device's
folder (``devices/<name>/law.py``) gives its controller law, excitation and limits,
``loops`` the laws as discrete transfer functions around a linear plant with margins
and predictions, ``frf`` the measured frequency responses. Nothing here knows a
device by name: generic code asks a ``DeviceLaws`` (the registry) for one.
"""
