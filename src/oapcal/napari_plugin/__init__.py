"""oapcal in napari (``docs/napari.md``): a plugin for the npe2 plugin engine.

Installed with the ``napari`` extra (in a clone of oapcal: ``pip install -e ".[napari]"``) and found by napari
through the ``napari.manifest`` entry point (the manifest is ``napari.yaml`` beside this
file).  It contributes

* a **reader** for oapcal calibration files (the distortion field as a vectors layer and a
  magnitude image, the calibration hull as a shapes layer) and for point-pair CSVs (two
  points layers, ``distorted`` and ``reference``, with the corner ``id`` as a feature);
* a **writer** of two points layers back to a point-pair CSV;
* **widgets**: *Detect* (USAF-1951 detection), *Label by hand* (register the target from a
  few clicked corners and propose the rest), *Fit & inspect* (fit or select a model, residual
  vectors, the paper's Table 1, parameters, worst landmarks) and *Correct* (correct an image
  or a stack, lazily for stacks; uncertainty map, hull; save the calibration);
* a **sample**: the demo's simulated camera image of USAF groups 4-5 through the relay.

Everything numerical goes through oapcal's public API; this package is a top layer beside
``cli`` (``docs/architecture.md``): nothing in oapcal imports it, and ``import oapcal`` does
not import napari or Qt.  Its modules import napari and Qt only inside the functions and
widgets that need them, so that ``_layers`` and ``_labelling`` run without a display.
"""
