"""Constants of stamp measurement, in a module without imports (read by option declarations)."""

#: The smallest stamp, in pixels.
MIN_STAMP_SIZE = 3
#: Coordinates of the first pixel's centre a catalog may use: 1 (FITS), 0 (GREAT3).
ORIGINS = (0, 1)
