"""fitmedia: absorption, scattering and anisotropy of liquids from photographs of a lit tank.

Internal units: millimetres and 1/mm.  Importing the package has no side
effects; Mitsuba and matplotlib are imported only by the functions that need them.
"""

__version__ = "0.1.0"
