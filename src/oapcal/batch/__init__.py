"""Correction of image files and stacks on disk (``oapcal correct``): expand the inputs, plan
the outputs, read frames (:mod:`oapcal.io.images`), remap them with
:func:`oapcal.imaging.remap.correct_image` and write them atomically and resumably
(:mod:`oapcal.batch.stack`), or one Dask task per chunk of frames
(:mod:`oapcal.batch.distributed`).  This layer sits above :mod:`oapcal.io`: the array work
stays in :mod:`oapcal.imaging`, the file formats in :mod:`oapcal.io`."""
