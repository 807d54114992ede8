"""uwbcl: UWB SAR radar processing for longwall coal mines.

Measures roof-support displacement -- retreat (advance along the panel, X) and creep (along the face,
Y) -- from squinted UWB SAR images of roof-bolt plates at two or more heights.
"""

__version__ = "0.1.0"
