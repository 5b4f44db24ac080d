"""Reconstruction stage of n2d: capture session to a textured, metric mesh (NeuS hash-grid SDF, fast
visual-hull path).
"""
