"""Dataset stage of n2d: bpy/Cycles generator of domain-randomised pose datasets with BOP and DOPE
annotations.
"""
