"""The flight recorder: every flight of the companion to MCAP files, viewable in Foxglove.

:mod:`schemas` (channels and their JSON Schemas), :mod:`messages` (record → JSON), :mod:`writer`
(the writer thread: rotation, size budget, failure), :mod:`recorder` (the loop's side),
:mod:`taps` (wrappers that report what the loop's parts did), :mod:`reader` (reading it back).
"""
