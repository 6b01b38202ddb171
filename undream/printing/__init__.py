"""Printing a texture: a CMYK printer's gamut as a projection, and the texture at its real size.

- :mod:`undream.printing.profiles`: where the CMYK profiles are (``gamut: default`` is the one
  setup fetched into the cache) and which one a run's ``gamut`` names;
- :mod:`undream.printing.gamut`: the projection of an sRGB texture onto what the printer
  reproduces (an ICC round trip through littleCMS, made idempotent on the 8-bit grid);
- :mod:`undream.printing.size`: a mesh's metres per texel from its triangles' 3D and UV areas;
- :mod:`undream.printing.export`: the texture as PNG and PDF at a print size and DPI.
"""
