"""oapcal: calibrate and remove the distortion of off-axis parabolic mirror relays.

The package is organised one module per concept, imports flowing one way::

    errors  <-  model  <-  fit  <-  select
                  ^         ^
    normalize, io (points, calibration)  <-  imaging, optics, report  <-  cli

Nothing imports :mod:`oapcal.cli` or :mod:`oapcal.report`.
"""

__version__ = "0.1.0"
