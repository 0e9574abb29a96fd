"""Tuning science shared by auto-tune, frequency response and what-if gains.

``frf`` estimates measured frequency responses; ``loops`` holds the devices' exact
discrete controller laws around a linear plant model, with margins and predictions.
Layering: numpy/scipy/python-control only; no imports from drivers, hub or api.
"""
