"""Stability and gain analysis: the push loops in the attempt domain (:mod:`.iteration`, eq 13-23) and the
30 Hz visual-servo loop (:mod:`.servo`).
"""
