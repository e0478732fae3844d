"""Identification: a rig's run logs → the parameters of the plant magctl models it with.

``magctl identify LOG… --out DIR`` (:mod:`magctl.identify.run`) reads logs written by ``magctl rig run``, cuts them
into the phases where each parameter shows (:mod:`magctl.identify.phases`), fits each parameter there
(:mod:`magctl.identify.camera`, :mod:`magctl.identify.actuation`, :mod:`magctl.identify.side`,
:mod:`magctl.identify.release`) and writes a complete parameter folder (:mod:`magctl.identify.folder`) in which
every identified value carries its uncertainty, the logs and frames it came from and its fit quality as its
source. docs/identify.md is the how-to.
"""
