"""Sensing: camera (lag, pixels, drops), a blackout gate, the tracker (Kalman) and a particle filter.

What a lab's own camera software replaces on a real rig.
"""
