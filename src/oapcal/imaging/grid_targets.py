"""Camera images of dot grids and chessboards through any distortion model, with the truth
of every landmark (``docs/detection.md``, "Dot grids and chessboards").

A :class:`GridTarget` is drawn as an area-sampled source image in the object plane (dots:
discs of ``dot_um`` on a ``pitch_um`` square lattice; a chessboard of ``rows x cols``
squares of ``pitch_um`` with a bright margin) and rendered through a :class:`~oapcal.imaging.render.Scene`
by :func:`oapcal.imaging.render.render_scene` (the camera's blur, pixel integration,
noise and quantization).  The truth is each landmark's camera position: dot centres and
the chessboard's inner corners, mapped from the source through the scene's exact forward
map (:meth:`~oapcal.imaging.render.Scene.camera_from_source`).

The paper's camera is the default (640 x 480, 4.8 um pixels, blur sigma 0.8 px, SNR 50,
8 bits); :func:`paper_relays` gives setup 1's relay aligned and two misaligned relays.

>>> t = GridTarget("dots", 3, 4, pitch_um=50.0, dot_um=25.0)
>>> t.ids[:2], t.landmarks_um().shape
(('R0C0', 'R0C1'), (12, 2))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.records import ImageSize

#: A landmark is *in view* when it lies at least this far inside the image (px) and, for a
#: dot, when the whole dot does (its radius + this margin).
VIEW_MARGIN_PX = 2.0
#: The relative transmission of the dark parts (chrome on glass; the simulator's background).
DARK_LEVEL = 0.05

#: The misaligned relays of :func:`paper_relays` (mirror tilts deg, decentres mm, d1 mm,
#: camera tilts deg, defocus mm: within the ranges of ``benchmarks/e2e_real.py``).
MISALIGNED = {
    "misaligned A": {"m2_tilt_x": 0.03, "m1_decentre_y": 0.15, "d1": 25.0, "camera_tilt_y": 0.5,
                     "camera_defocus": 0.1},
    "misaligned B": {"m1_tilt_y": -0.04, "m2_decentre_x": -0.2, "d1": -30.0, "camera_tilt_x": -0.8,
                     "camera_tilt_y": 0.3},
}  # fmt: skip


@dataclass(frozen=True)
class GridTarget:
    """A dot grid (``kind="dots"``: ``rows x cols`` dots of ``dot_um`` diameter at
    ``pitch_um``) or a chessboard (``kind="chessboard"``: ``rows x cols`` squares of
    ``pitch_um``, whose landmarks are the ``(rows - 1) x (cols - 1)`` inner corners).
    ``dark_features`` draws dark dots on a bright field (a chrome-on-glass target in
    transmission); a chessboard's top-left square is dark.  Landmark ids are
    ``R{row}C{col}``, row 0 at the top of the target as drawn (its -y side)."""

    kind: str
    rows: int
    cols: int
    pitch_um: float
    dot_um: float | None = None
    dark_features: bool = True

    def __post_init__(self):
        if self.kind not in ("dots", "chessboard"):
            raise DataError(f"kind {self.kind!r}: use 'dots' or 'chessboard'", param="kind")
        if int(self.rows) < 2 or int(self.cols) < 2:
            raise DataError(f"{self.rows} x {self.cols}: a grid needs at least 2 x 2", param=("rows", "cols"))
        if not self.pitch_um > 0:
            raise DataError(f"pitch_um {self.pitch_um}: must be positive", param="pitch_um")
        if self.kind == "dots" and not (self.dot_um is not None and 0 < self.dot_um < self.pitch_um):
            raise DataError(f"dot_um {self.dot_um}: a dot grid needs 0 < dot_um < pitch_um", param="dot_um")

    @property
    def shape(self) -> tuple[int, int]:
        """Landmark rows and columns."""
        if self.kind == "dots":
            return int(self.rows), int(self.cols)
        return int(self.rows) - 1, int(self.cols) - 1

    @property
    def rc(self) -> np.ndarray:
        r, c = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return np.stack([r.ravel(), c.ravel()], axis=1)

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(f"R{r}C{c}" for r, c in self.rc)

    def landmarks_um(self) -> np.ndarray:
        """Landmark positions ``(x, y)`` um about the target's centre."""
        rc = self.rc.astype(float)
        n_r, n_c = self.shape
        return np.stack([(rc[:, 1] - (n_c - 1) / 2), (rc[:, 0] - (n_r - 1) / 2)], axis=1) * self.pitch_um

    def extent_um(self) -> float:
        """Half the side of the square that holds the target and a margin."""
        return 0.5 * max(self.rows, self.cols) * self.pitch_um + 1.5 * self.pitch_um

    def source(self, um_per_px: float) -> tuple[np.ndarray, tuple[float, float]]:
        """The target as an area-sampled image at ``um_per_px`` (relative transmission, bright
        1) and the source pixel of the target's centre."""
        half = self.extent_um()
        n = int(np.ceil(2 * half / um_per_px))
        if n * n > 64_000_000:
            raise DataError(
                f"a source of {n} x {n} px is too large: use a coarser um_per_px", param="um_per_px"
            )
        centre = (n - 1) / 2.0
        sub = 4  # 4 x 4 samples per source pixel: area sampling of the edges
        off = (np.arange(sub) + 0.5) / sub - 0.5
        coord = ((np.arange(n)[:, None] + off[None, :]).ravel() - centre) * um_per_px  # um
        dark = np.zeros((n * sub, n * sub), np.float32)
        if self.kind == "dots":
            r = 0.5 * self.dot_um

            def along(n_nodes):  # offset of each sample from its nearest node (dots << pitch)
                k = np.clip(np.round(coord / self.pitch_um + (n_nodes - 1) / 2), 0, n_nodes - 1)
                return (coord - (k - (n_nodes - 1) / 2) * self.pitch_um).astype(np.float32)

            dx, dy = along(self.cols), along(self.rows)
            dark = (dx[None, :] ** 2 + dy[:, None] ** 2) <= np.float32(r * r)
        else:
            w = self.cols * self.pitch_um / 2
            hgt = self.rows * self.pitch_um / 2
            ix = np.floor((coord + w) / self.pitch_um)
            iy = np.floor((coord + hgt) / self.pitch_um)
            inside_x = (coord >= -w) & (coord < w)
            inside_y = (coord >= -hgt) & (coord < hgt)
            dark = (((ix[None, :] + iy[:, None]) % 2) == 0) & inside_x[None, :] & inside_y[:, None]
        cover = dark.reshape(n, sub, n, sub).mean(axis=(1, 3), dtype=np.float32)
        if self.dark_features:
            img = 1.0 - (1.0 - DARK_LEVEL) * cover
        else:
            img = DARK_LEVEL + (1.0 - DARK_LEVEL) * cover
        return img.astype(np.float32), (centre, centre)


@dataclass(frozen=True)
class GridRendering:
    """A rendered target: ``image``, the truth ``ids``, ``rc`` (row, col on the target),
    ``xy_d`` (camera px) and ``in_view`` per landmark, the ``scene`` and the target, the
    noise-free ``clean`` image and ``object_um`` the true object point (um, about the axis)
    of every pixel centre ``(h, w, 2)`` (NaN where the model's inverse failed)."""

    image: np.ndarray
    ids: tuple[str, ...]
    rc: np.ndarray
    xy_d: np.ndarray
    in_view: np.ndarray
    scene: object
    target: GridTarget
    clean: np.ndarray
    object_um: np.ndarray


def paper_relays() -> dict:
    """Setup 1's relay at the paper's camera, aligned and misaligned (:data:`MISALIGNED`):
    name -> relay parameter vector."""
    from oapcal.optics.relay_model import RelayDesign, relay_params

    design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
    out = {"aligned": relay_params(design)}
    for name, mis in MISALIGNED.items():
        out[name] = relay_params(design, mis)
    return out


def render_grid(
    target: GridTarget,
    params=None,
    *,
    camera=None,
    rotation_deg: float = 0.0,
    offset_um=(0.0, 0.0),
    mirror: bool = False,
    source_um_per_px: float | None = None,
    seed: int = 0,
) -> GridRendering:
    """Render ``target`` through the model ``params`` (any family; default the setup-1-like
    Eq. (1) field of :mod:`oapcal.imaging.field`) at ``camera`` (default the paper's:
    :class:`oapcal.imaging.render.Camera`), the target turned by ``rotation_deg`` (and
    mirrored) with its centre ``offset_um`` from the optical axis; the source is drawn at
    ``source_um_per_px`` (default: a tenth of the dot or square, each source pixel area-sampled
    by 4 x 4 samples)."""
    from oapcal.imaging.field import SETUP1_LIKE
    from oapcal.imaging.render import Camera, Placement, Scene, render_scene

    camera = Camera() if camera is None else camera
    params = SETUP1_LIKE if params is None else np.asarray(params, float)
    feature = target.dot_um if target.kind == "dots" else target.pitch_um
    step = float(source_um_per_px) if source_um_per_px else feature / 10.0
    src, centre = target.source(step)
    # the target's centre sits offset_um from the axis: the source point on the axis is the
    # target point at -offset
    off = np.asarray(offset_um, float)
    placement0 = Placement(
        step,
        centre,
        rotation_deg=rotation_deg,
        mirror=mirror,
        background=1.0 if target.dark_features else DARK_LEVEL,
    )
    axis_src = np.asarray(centre) - placement0.matrix() @ off
    placement = Placement(step, tuple(axis_src), rotation_deg=rotation_deg, mirror=mirror,
                          background=placement0.background)  # fmt: skip
    scene = Scene(params, placement, camera)
    r = render_scene(src, scene, seed=seed)
    lm_src = np.asarray(centre) + target.landmarks_um() / step  # source px (x right, y down)
    xy_d = scene.camera_from_source(lm_src)
    margin = VIEW_MARGIN_PX
    if target.kind == "dots":
        margin += 0.5 * target.dot_um / scene.camera_um_per_px
    else:
        margin += 0.25 * target.pitch_um / scene.camera_um_per_px
    in_view = ImageSize(*camera.size).contains(xy_d, margin)
    return GridRendering(r.image, target.ids, target.rc, xy_d, in_view, scene, target, r.clean, r.object_um)


__all__ = ["GridRendering", "GridTarget", "MISALIGNED", "paper_relays", "render_grid"]
