"""The on-disk contracts every stage shares, as plain readers (and the writers two stages need): the capture
session (`session`), the model directory (`model`), the printed calibration board (`board`). Stages import these,
never each other. docs/formats.md documents the formats.
"""
