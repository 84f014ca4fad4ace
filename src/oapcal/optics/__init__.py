"""Optics: exact real-ray tracing of off-axis parabolic mirror (OAP) relays.

* :mod:`~oapcal.optics.surfaces` paraboloid and plane surfaces (closed-form intersection,
  normals, reflection), :mod:`~oapcal.optics.trace` sequential tracing;
* :mod:`~oapcal.optics.relay` the paper's relay, chief-ray aiming, grid distortion;
* :mod:`~oapcal.optics.field` a dense distortion field in camera px
  (:func:`relay_distortion`);
* :mod:`~oapcal.optics.quality` spot diagrams and resolution limits.

Importing this package is cheap; the submodules load NumPy/SciPy.
"""


def relay_distortion(*args, **kwargs):
    """See :func:`oapcal.optics.field.relay_distortion`."""
    from oapcal.optics.field import relay_distortion as _relay_distortion

    return _relay_distortion(*args, **kwargs)


def __getattr__(name):
    if name == "DistortionField":
        from oapcal.optics.field import DistortionField

        return DistortionField
    raise AttributeError(name)
