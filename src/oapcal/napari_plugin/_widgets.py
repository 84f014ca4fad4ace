"""The plugin's dock widgets (magicgui containers; ``docs/napari.md``).

Each widget takes the viewer (npe2 passes it), runs its long step in a napari thread worker
(the viewer stays responsive; a busy bar in the widget and napari's activity panel show it)
and reports the outcome in its status line.  A failure (bad input, a target that cannot be
found) is shown as a notification and in the status line with oapcal's one-line reason,
never as a traceback.  ``widget.busy`` is True while a worker runs; ``widget.worker`` is the
last one started.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    LineEdit,
    ProgressBar,
    PushButton,
    SpinBox,
    Table,
)

from oapcal.napari_plugin import _layers as L
from oapcal.records import ImageSize
from oapcal.select import FRAME_TERMS, with_frame_terms  # noqa: F401 (FRAME_TERMS: the name as before)

#: Models offered by *Fit & inspect*: oapcal's presets and AICc selection.
SELECT = "select (AICc)"
#: Widest a docked widget grows (px), so that the canvas keeps most of the window.
MAX_WIDTH_PX = 460
#: Step (px) of the uncertainty map the *Correct* widget shows.
UNCERTAINTY_STEP = 4


def _message(exc: BaseException) -> str:
    """One line for the user: oapcal's own message, or the exception's type and text."""
    from oapcal.errors import OapcalError

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return text if isinstance(exc, OapcalError) else f"{type(exc).__name__}: {text}"


def _layers_of(viewer, kind: str):
    import napari.layers

    cls = {"image": napari.layers.Image, "points": napari.layers.Points}[kind]
    return [(layer.name, layer) for layer in viewer.layers if isinstance(layer, cls)]


def _plane(layer, viewer) -> np.ndarray:
    """The 2-D (or RGB) plane of an image layer that the viewer shows."""
    data = layer.data
    spatial = 3 if layer.rgb else 2
    if data.ndim > spatial:
        step = viewer.dims.current_step[: data.ndim - spatial]
        data = data[tuple(int(min(max(s, 0), n - 1)) for s, n in zip(step, data.shape))]
    return np.asarray(data)


def _replace_layer(viewer, layer_tuple):
    """Add a layer from a layer data tuple, replacing a layer of the same name."""
    data, kwargs, kind = layer_tuple
    name = kwargs.get("name")
    if name in viewer.layers:
        viewer.layers.remove(name)
    return getattr(viewer, f"add_{kind}")(data, **kwargs)


class _OapcalWidget(Container):
    """A container with a status line, a busy bar and a thread-worker runner."""

    step_name = "oapcal"

    def __init__(self, napari_viewer, widgets):
        self._status = Label(value="")
        self._busy_bar = ProgressBar(min=0, max=0, visible=False, label="working")
        # scrollable: docked widgets never make the window taller than a 1080 px screen
        super().__init__(widgets=[*widgets, self._busy_bar, self._status], labels=True, scrollable=True)
        self._status.native.setWordWrap(True)
        self.root_native_widget._magic_widget = self  # napari finds the widget from its dock
        from qtpy.QtCore import Qt

        scroll = self.root_native_widget  # the fields wrap to the dock's width; only vertical scrolling
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        bar = scroll.verticalScrollBar().sizeHint().width() + 2 * scroll.frameWidth()
        scroll.widget().setMaximumWidth(MAX_WIDTH_PX - bar)
        # one width: the fields' own (their table, say) may grow after they are shown, and
        # the scroll area would clip what its viewport cannot show
        scroll.setFixedWidth(MAX_WIDTH_PX)
        scroll.widget().layout().addStretch(1)  # the fields at the top, as napari docks a plain widget
        self.viewer = napari_viewer
        self.busy = False
        self.worker = None
        #: The progress a running step reported last, and all it reported (``(done, total,
        #: stage)``; written by the worker thread, shown by a timer in the main thread).
        self.progress_log: list[tuple] = []
        self._timer = None
        self.last_error: str | None = None
        napari_viewer.layers.events.inserted.connect(self._refresh)
        napari_viewer.layers.events.removed.connect(self._refresh)
        napari_viewer.layers.events.reordered.connect(self._refresh)
        self.reset_choices()  # the choices that need the viewer (it was not set while they were made)

    @property
    def native(self):
        """The scroll area around the fields: what napari docks (it docks ``native``), so that a
        docked widget scrolls instead of making the window taller than the screen."""
        return self.root_native_widget

    def _refresh(self, _event=None):
        self.reset_choices()

    @property
    def status(self) -> str:
        return str(self._status.value)

    def _set_status(self, text: str) -> None:
        self._status.value = text

    def _fail(self, message: str) -> None:
        from napari.utils.notifications import show_warning

        self.last_error = message
        self._set_status(f"{self.step_name} failed: {message}")
        show_warning(f"oapcal {self.step_name.lower()}: {message}")

    def _chosen_image(self):
        """The image layer chosen in the widget, or None (and the reason shown)."""
        layer = self.image.value
        if layer is None:
            self._fail("open an image first (no image layer)")
        return layer

    def _run(self, what: str, func, done, *, steps: bool = False) -> None:
        """Run ``func()`` in a thread worker; ``done(result)`` in the main thread after it.
        Exceptions (and ``done``'s own) become :meth:`_fail` messages.  With ``steps``,
        ``func(progress)`` gets a progress callback (:mod:`oapcal.progress`) and the busy bar
        shows its count and stage."""
        from napari.qt.threading import create_worker

        if self.busy:
            self._set_status(f"busy: {what} waits until the running step ends")
            return

        self.progress_log = log = []

        def safe():
            try:
                return True, func(lambda *report: log.append(report)) if steps else func()
            except Exception as exc:  # shown to the user, not raised into Qt
                return False, _message(exc)

        def finish(out):
            ok, value = out
            try:
                if ok:
                    done(value)
                else:
                    self._fail(value)
            except Exception as exc:
                self._fail(_message(exc))
            finally:
                if self._timer is not None:
                    self._timer.stop()
                self.busy = False
                self._busy_bar.visible = False

        self.busy = True
        self.last_error = None
        self._busy_bar.max = 0  # busy until a step reports a count
        self._busy_bar.visible = True
        self._set_status(f"{what}...")
        if steps:
            self._start_timer(what)
        self.worker = create_worker(safe, _progress={"desc": f"oapcal: {what}"})
        self.worker.returned.connect(finish)
        self.worker.start()

    def _start_timer(self, what: str) -> None:
        """Show the worker's progress every 100 ms (Qt widgets change in the main thread only)."""
        from qtpy.QtCore import QTimer

        self._timer = QTimer()
        self._timer.setInterval(100)
        self._timer.timeout.connect(lambda: self._show_progress(what))
        self._timer.start()

    def _show_progress(self, what: str) -> None:
        """The last reported ``(done, total, stage)`` on the busy bar and status line."""
        if not self.progress_log:
            return
        done, total, stage = (tuple(self.progress_log[-1]) + ("",))[:3]
        self._busy_bar.max = max(int(total), 1)
        self._busy_bar.value = min(int(done), int(total))
        self._set_status(f"{what}: {stage}..." if stage else f"{what}...")


class DetectWidget(_OapcalWidget):
    """USAF-1951 detection (:func:`oapcal.detect_usaf`, oapcal's defaults) on the shown plane
    of an image layer; adds the ``distorted`` and ``reference`` points layers with ids."""

    step_name = "Detect"
    #: The points layer where the user clicks the element named in the anchor field.
    ANCHOR_LAYER = "anchor"

    def __init__(self, napari_viewer):
        self.image = ComboBox(label="image", choices=lambda _w: _layers_of(napari_viewer, "image"))
        self.groups = LineEdit(label="groups", value="4-5")
        self.um_per_px = FloatSpinBox(label="um per px (0: find)", value=0.0, min=0.0, max=1e6, step=0.1)
        from oapcal.imaging.usaf import ORIENTATIONS

        self.orient = ComboBox(label="orientation", choices=["auto", *ORIENTATIONS], value="auto")
        self.mirror = ComboBox(label="mirror", choices=["auto", "yes", "no"], value="auto")
        self.max_stderr_px = FloatSpinBox(label="max stderr (px)", value=0.3, min=0.01, max=10.0, step=0.05)
        # the command's --anchor: elements the user reads on the target, e.g. "G4E2@512,300"
        # (where it is, in the image's px: x then y); several separated by spaces
        self.anchor = LineEdit(label="anchor (e.g. G4E2@x,y)", value="")
        # or the element's name alone and a click on it: the click gives the @x,y
        self.pick = PushButton(text="Click the element named")
        self.pick.changed.connect(self.pick_anchor)
        self.button = PushButton(text="Detect")
        self.button.changed.connect(self.run)
        fields = [self.image, self.groups, self.um_per_px, self.orient, self.mirror, self.max_stderr_px]
        super().__init__(napari_viewer, [*fields, self.anchor, self.pick, self.button])
        self.detection = None

    def pick_anchor(self, _=None):
        """The ``anchor`` points layer in add mode: a click on the element whose numbers the
        user reads gives its place; the anchor field then needs only its name (``G7E1``)."""
        if self.ANCHOR_LAYER not in self.viewer.layers:
            self.viewer.add_points(np.zeros((0, 2)), name=self.ANCHOR_LAYER, face_color="yellow", size=12)
        layer = self.viewer.layers[self.ANCHOR_LAYER]
        layer.mode = "add"
        self.viewer.layers.selection.active = layer
        self._set_status(
            "click the element whose numbers you read, type its name (e.g. G4E2) in anchor, Detect"
        )
        return layer

    def anchor_text(self) -> str:
        """The anchor field, with the last click on the ``anchor`` layer as the place of an
        element named without one (``G7E1`` and a click at column 300, row 560: ``G7E1@300,560``)."""
        words = self.anchor.value.replace(";", " ").split()
        if len(words) != 1 or "@" in words[0] or self.ANCHOR_LAYER not in self.viewer.layers:
            return " ".join(words)
        clicks = self.viewer.layers[self.ANCHOR_LAYER].data
        if not len(clicks):
            return words[0]
        x, y = L.rc_to_xy(clicks[-1:])[0]
        return f"{words[0]}@{x:.0f},{y:.0f}"

    def run(self, _=None) -> None:
        import oapcal
        from oapcal.imaging.usaf import parse_groups

        layer = self._chosen_image()
        if layer is None:
            return
        from oapcal.imaging.detect.anchor import parse_anchors

        try:
            groups = parse_groups(self.groups.value)
            anchors = parse_anchors(self.anchor_text().split())
        except Exception as exc:
            self._fail(_message(exc))
            return
        image = _plane(layer, self.viewer)
        kwargs = {"um_per_px": self.um_per_px.value or None, "orientation": self.orient.value,
                  "mirror": self.mirror.value, "max_stderr_px": self.max_stderr_px.value,
                  "anchors": anchors}  # fmt: skip

        def done(det):
            self.detection = det
            if det.status != 0:
                # the library's advice names the parameter; here it is the anchor field
                self._fail(det.message.replace(" in anchors", " in the anchor field"))
                return
            layers = L.points_layers(det.xy_u, det.xy_d, det.ids, um_per_px=det.um_per_px,
                                     source=layer.name, extra={"stderr_px": det.stderr_px})  # fmt: skip
            for t in layers:
                _replace_layer(self.viewer, t)
            sigma = f" +/- {det.um_per_px_sigma:.2g}" if det.um_per_px_sigma is not None else ""
            self._set_status(
                f"{len(det.ids)} of {det.n_expected} corners, {det.um_per_px:.4g}{sigma} um/px, "
                f"orientation {det.orientation}, blur {det.sigma_px:.2f} px"
            )

        def work(progress):
            return oapcal.detect_usaf(image, groups, progress=progress, **kwargs)

        self._run("detect", work, done, steps=True)


class LabelWidget(_OapcalWidget):
    """Label by hand: click a few corners with their ids, then let oapcal propose the rest
    (:mod:`oapcal.napari_plugin._labelling`), optionally refined by detection at the pose the
    clicks give; the proposal becomes the ``distorted``/``reference`` layers, which can be
    edited (drag, delete) before fitting."""

    step_name = "Label by hand"
    LAYER = "hand labels"

    def __init__(self, napari_viewer):
        self.image = ComboBox(label="image", choices=lambda _w: _layers_of(napari_viewer, "image"))
        self.groups = LineEdit(label="groups", value="4-5")
        self.corner = ComboBox(label="next corner id", choices=self._ids)
        self.um_per_px = FloatSpinBox(
            label="um per px (0: from clicks)", value=0.0, min=0.0, max=1e6, step=0.1
        )
        from oapcal.imaging.usaf import LAYOUTS

        self.target_layout = ComboBox(label="target layout", choices=["auto", *LAYOUTS], value="auto")
        self.refine = CheckBox(label="refine with detection", value=True)
        self.start = PushButton(text="Start labelling")
        self.propose = PushButton(text="Propose the other corners")
        self.start.changed.connect(self.start_labelling)
        self.propose.changed.connect(self.run)
        self.corner.changed.connect(self._corner_changed)
        self.groups.changed.connect(lambda _v: self.corner.reset_choices())
        fields = [self.image, self.groups, self.corner, self.um_per_px, self.target_layout, self.refine]
        super().__init__(napari_viewer, [*fields, self.start, self.propose])
        self.proposal = None

    def _ids(self, _w=None):
        import oapcal
        from oapcal.imaging.usaf import parse_groups

        try:
            return list(oapcal.usaf_target(parse_groups(self.groups.value)).corner_ids)
        except Exception:
            return []

    def _corner_changed(self, value) -> None:
        if self.LAYER in self.viewer.layers and value:
            self.viewer.layers[self.LAYER].feature_defaults["id"] = value

    def start_labelling(self, _=None):
        """The ``hand labels`` points layer in add mode; each click gets the selected id."""
        if self.LAYER not in self.viewer.layers:
            layer = self.viewer.add_points(
                np.zeros((0, 2)), name=self.LAYER, features={"id": np.array([], dtype=object)},
                face_color="magenta", size=7, text={"string": "{id}", "size": 8, "color": "magenta",
                                                    "translation": np.array([-8.0, 0.0])},
            )  # fmt: skip
        layer = self.viewer.layers[self.LAYER]
        layer.feature_defaults["id"] = self.corner.value
        layer.events.data.connect(self._advance)
        layer.mode = "add"
        self.viewer.layers.selection.active = layer
        self._set_status(f"click corner {self.corner.value}; choose the id before each click")
        return layer

    def _advance(self, event=None) -> None:
        """After a click, select the next id not yet placed (the user may choose another)."""
        if getattr(event, "action", None) not in (None, "added"):
            return
        placed = set(
            L.layer_ids(self.viewer.layers[self.LAYER].data, self.viewer.layers[self.LAYER].features)
        )
        ids = self._ids()
        if self.corner.value in ids:
            k = ids.index(self.corner.value)
            for i in ids[k + 1 :] + ids[:k]:
                if i not in placed:
                    self.corner.value = i
                    break

    def clicks(self) -> dict:
        """The ``hand labels`` layer as id -> (x, y) image px."""
        if self.LAYER not in self.viewer.layers:
            return {}
        layer = self.viewer.layers[self.LAYER]
        ids = L.layer_ids(layer.data, layer.features)
        return dict(zip(ids, map(tuple, L.rc_to_xy(layer.data))))

    def run(self, _=None) -> None:
        import oapcal
        from oapcal.imaging.usaf import parse_groups
        from oapcal.napari_plugin._labelling import propose_corners, refine_with_detection

        layer = self._chosen_image()
        if layer is None:
            return
        image = _plane(layer, self.viewer)
        size = ImageSize.of(image)
        clicks = self.clicks()
        refine = self.refine.value
        um = self.um_per_px.value or None
        groups_text = self.groups.value
        layout_name = self.target_layout.value

        def work():
            groups = parse_groups(groups_text)
            prop = propose_corners(clicks, size, groups, um, layout_name)
            det = None
            if refine:
                hints = {"um_per_px": prop.um_per_px, "orientation": prop.orientation,
                         "mirror": "yes" if prop.mirrored else "no"}  # fmt: skip
                det = oapcal.detect_usaf(image, groups, **hints)
                prop = refine_with_detection(prop, det, size, groups, um)
            return prop, det

        def done(out):
            prop, det = out
            self.proposal = prop
            detected = det is not None and det.status == 0
            source = np.full(len(prop.ids), "detected", object) if detected else (
                np.where(prop.clicked, "clicked", "proposed").astype(object))  # fmt: skip
            for t in L.points_layers(prop.xy_u, prop.xy_d, prop.ids, um_per_px=prop.um_per_px,
                                     source=layer.name, extra={"source": source}):  # fmt: skip
                _replace_layer(self.viewer, t)
            self._set_status(_proposal_words(prop, det, clicks))

        self._run("propose", work, done)


def _proposal_words(prop, det, clicks) -> str:
    """The Label widget's status line after a proposal (and the detection that refined it)."""
    head = (f"{len(prop.ids)} corners from a {prop.map_kind} map ({prop.layout} layout), "
            f"{prop.um_per_px:.4g} um/px, {prop.orientation}, clicks off the map by "
            f"{prop.click_rms_px:.2g} px rms")  # fmt: skip
    if det is None:
        return (f"{head}; {int(prop.clicked.sum())} clicked, the others proposed (neither is sub-pixel: "
                "drag them onto their corners, or tick 'refine with detection'), then fit")  # fmt: skip
    if det.status != 0:
        return (f"{head}; detection at that pose: {det.message} (the corners are the clicked and "
                "proposed ones, not sub-pixel: drag them onto their corners before fitting)")  # fmt: skip
    lost = [i for i in prop.dropped if i in clicks]
    words = f"{head}; detection at that pose found {len(det.ids)}, all sub-pixel"
    if lost:
        more = f" and {len(lost) - 5} more" if len(lost) > 5 else ""
        words += (f"; left out {len(lost)} clicked corner{'s' * (len(lost) > 1)} that detection did not "
                  f"find ({', '.join(lost[:5])}{more}; a click is not sub-pixel)")  # fmt: skip
    if len(prop.dropped) > len(lost):
        words += f"; left out {len(prop.dropped) - len(lost)} proposed corners that detection did not find"
    return words + "; then fit"


class FitWidget(_OapcalWidget):
    """Fit a model (or select one by AICc) to the ``distorted``/``reference`` layers
    (:func:`oapcal.calibrate`); show the residual vectors, the paper's Table 1, the
    parameters and the worst landmarks."""

    step_name = "Fit"

    def __init__(self, napari_viewer):

        points = lambda _w: _layers_of(napari_viewer, "points")  # noqa: E731
        self.distorted = ComboBox(label="distorted", choices=points)
        self.reference = ComboBox(label="reference", choices=points)
        self.model = ComboBox(label="model", choices=_model_choices(), value=RECOMMENDED)
        self.um_per_px = FloatSpinBox(
            label="um per px (0: from layers)", value=0.0, min=0.0, max=1e6, step=0.1
        )
        # the relay's design (relay models only), as oapcal fit --relay-setup / --relay-pixel-size /
        # --microscope-magnification / --priors
        self.relay_setup = ComboBox(label="relay setup", choices=[1, 2], value=1)
        self.relay_pixel = FloatSpinBox(label="relay camera pixel (um)", value=4.8, min=0.01, max=1e3)
        self.microscope = FloatSpinBox(
            label="microscope magnification (0: none)", value=0.0, min=-1e3, max=1e3
        )
        # the relay's priors on by default, as oapcal fit's --priors auto
        self.priors = ComboBox(label="relay priors", choices=["off", "default"], value="default")
        self.model.changed.connect(self._show_relay_fields)
        self.n_worst = SpinBox(label="worst landmarks", value=5, min=0, max=100)
        self.exaggerate = FloatSpinBox(label="residual arrows x", value=20.0, min=1.0, max=1000.0)
        self.button = PushButton(text="Fit")
        self.button.changed.connect(self.run)
        self.table1 = Label(label="Table 1", value="")
        self.table1.native.setStyleSheet("font-family: monospace")
        self.params = Table(label="parameters", value={"parameter": [], "value": [], "stderr": []})
        self.worst_text = Label(label="worst", value="")
        relay = [self.relay_setup, self.relay_pixel, self.microscope, self.priors]
        super().__init__(napari_viewer, [self.distorted, self.reference, self.model, *relay, self.um_per_px,
                                         self.n_worst, self.exaggerate, self.button, self.table1,
                                         self.params, self.worst_text])  # fmt: skip
        self._show_relay_fields()
        self.calibration = None
        self.residual_px = None
        self.ids: list[str] = []
        self._default_layers()

    def _show_relay_fields(self, _=None):
        from oapcal.entry import is_relay_spec

        relay = is_relay_spec(self.model.value)
        for w in (self.relay_setup, self.relay_pixel, self.microscope, self.priors):
            w.visible = relay

    def _default_layers(self):
        for combo, name in ((self.distorted, L.DISTORTED), (self.reference, L.REFERENCE)):
            if name in self.viewer.layers:
                combo.value = self.viewer.layers[name]

    def _refresh(self, _event=None):
        super()._refresh()
        self._default_layers()

    def run(self, _=None) -> None:
        import oapcal

        d_layer, r_layer = self.distorted.value, self.reference.value
        if d_layer is None or r_layer is None or d_layer is r_layer:
            self._fail("choose two points layers: distorted and reference (detect or label first)")
            return
        try:
            xy_u, xy_d, ids = L.pair_layers(
                (d_layer.data, d_layer.features), (r_layer.data, r_layer.features)
            )
        except Exception as exc:
            self._fail(_message(exc))
            return
        scale = self.um_per_px.value or d_layer.metadata.get(L.SCALE) or r_layer.metadata.get(L.SCALE)
        model = self.model.value
        image = next((lay for lay in self.viewer.layers if lay.__class__.__name__ == "Image"), None)
        size = None
        if image is not None:
            shape = image.data.shape[-3:-1] if image.rgb else image.data.shape[-2:]
            size = (int(shape[1]), int(shape[0]))

        relay = self._relay_options(model)

        def work():
            if model == SELECT:
                chosen = with_frame_terms(oapcal.select_models(xy_u, xy_d))  # the shared default start
            else:
                chosen = model
            return oapcal.calibrate(xy_u, xy_d, chosen, um_per_px=scale, image_size=size,
                                    name=f"{model} fit in napari", source=d_layer.name, **relay)  # fmt: skip

        def done(cal):
            self.show_calibration(cal, xy_u, xy_d, ids)

        self._run("fit", work, done)

    def _relay_options(self, model: str) -> dict:
        """``design`` and ``priors`` of a relay model from the widget's fields (else none)."""
        from oapcal.entry import is_relay_spec
        from oapcal.optics.relay_model import RelayDesign, parse_priors

        if not is_relay_spec(model):
            return {}
        design = RelayDesign(setup=int(self.relay_setup.value), pixel_size_um=float(self.relay_pixel.value),
                             microscope_magnification=float(self.microscope.value) or None)  # fmt: skip
        return {"design": design, "priors": parse_priors(self.priors.value)}

    def show_calibration(self, cal, xy_u, xy_d, ids) -> None:
        """Show a calibration's residuals, Table 1, parameters and worst landmarks."""
        self.calibration = cal
        res = L.residual_vectors(cal, xy_u, xy_d, ids, exaggerate=self.exaggerate.value)
        self.residual_px = res["residual_px"]
        self.ids = list(ids)
        for name in [lay.name for lay in self.viewer.layers if lay.name.startswith("residuals (x")]:
            self.viewer.layers.remove(name)
        _replace_layer(self.viewer, res["layer"])
        worst = res["worst"][: self.n_worst.value]
        if len(worst):
            text = {"string": "{id}", "size": 9, "color": "red", "translation": np.array([-10.0, 0.0])}
            _replace_layer(self.viewer, (L.xy_to_rc(xy_d[worst]), {
                "name": "worst landmarks", "features": {"id": np.array(ids, object)[worst],
                                                        "residual_px": res["residual_px"][worst]},
                "symbol": "ring", "size": 10, "face_color": "transparent", "border_color": "red",
                "text": text, "metadata": {L.CALIBRATION: cal}}, "points"))  # fmt: skip
        self.worst_text.value = "\n".join(f"{ids[k]}: {res['residual_px'][k]:.3g} px" for k in worst)
        self.table1.value = L.table1_text(cal.residuals)
        names = list(cal.free)
        self.params.value = {
            "parameter": names,
            "value": [f"{cal.params_dict[n]:.6g}" for n in names],
            "stderr": [f"{s:.3g}" for s in cal.stderr[list(cal.mask.nonzero()[0])]],
        }
        state = "converged" if cal.fit.converged else f"did NOT converge ({cal.fit.message})"
        notes = "".join(f"; {note}" for note in cal.notes)
        trust = _trust_words(cal)
        self._set_status(f"{cal.fit.n_points} pairs, model {', '.join(cal.free)}: {state}; "
                         f"mean residual {cal.residuals.mean_px:.3g} px{notes}{trust}")  # fmt: skip


#: The model *Fit & inspect* preselects: the paper's (``oapcal fit``'s default; with
#: ``rotation="auto"`` the target's rotation is fitted too when the points need it).
RECOMMENDED = "paper"


def _model_choices() -> list[tuple[str, str]]:
    """Every model family a fit can use, as ``(label, model spec)``: the Eq. (1) presets,
    the same with the target's rotation and with the camera's tilt too, the physical relay
    (``relay+microscope`` when the microscope's magnification is given) and AICc selection;
    the recommended one says so."""
    import oapcal

    # with the target's rotation, and with the camera's tilt (keystone) as well
    turned = [f"{name}+rotation" for name in oapcal.PRESETS]
    eq1 = [*oapcal.PRESETS, *turned, *(f"{name}+tilt" for name in turned)]
    # the relay family with a microscope behind it (relay+microscope) is the relay with the
    # microscope's magnification given in its design
    labels = {RECOMMENDED: f"{RECOMMENDED} (recommended)", "relay": "relay (physical: the design below)"}
    return [(labels.get(m, m), m) for m in [*eq1, "relay", SELECT]]


def _trust_words(cal) -> str:
    """``"; predicted error <= 1 px over 26 % of the image (floor ..., extrapolation x...)"``:
    the calibration's trust region over its image (empty without an image size)."""
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX
    from oapcal.uncertainty import uncertainty_map

    if not cal.image_size or not cal.fit.converged:
        return ""
    w, h = cal.image_size
    umap = uncertainty_map(cal, (h, w), step=max(1, max(w, h) // 64))
    share = float(umap.trusted(DEFAULT_MAX_ERROR_PX).mean())
    em = cal.error_model
    how = "" if em is None else f" (floor {em.floor_px:.2g} px, extrapolation x{em.extrapolation:.2g})"
    return f"; predicted error <= {DEFAULT_MAX_ERROR_PX:g} px over {100 * share:.0f} % of the image{how}"


def _trust_status(unc, limit: float, trust_only: bool) -> str:
    """The status line's trust region part (empty without an uncertainty map)."""
    if unc is None:
        return ""
    share = float(unc.trusted(limit).mean())
    written = "only it written" if trust_only else "the whole frame written"
    return f"; trust region (predicted error <= {limit:g} px): {100 * share:.0f} % of the frame, {written}"


class CorrectWidget(_OapcalWidget):
    """Correct an image or a stack (lazily, frame by frame, for stacks) with a calibration
    (from *Fit & inspect*, a layer opened from a calibration file, or a file); show the
    uncertainty map and the calibration hull; save the calibration."""

    step_name = "Correct"

    def __init__(self, napari_viewer):
        from oapcal.imaging.remap import INTERPOLATIONS

        self.image = ComboBox(label="image", choices=lambda _w: _layers_of(napari_viewer, "image"))
        self.source = ComboBox(label="calibration", choices=self._calibrations)
        self.file = FileEdit(label="or file", mode="r", filter="*.json", value="")
        self.interp = ComboBox(label="interpolation", choices=list(INTERPOLATIONS), value="cubic")
        self.show_uncertainty = CheckBox(label="uncertainty map", value=True)
        self.trust_only = CheckBox(label="only the trust region", value=False)
        self.max_error = FloatSpinBox(
            label="max predicted error (px)", value=1.0, min=0.01, max=1e4, step=0.1
        )
        self.show_hull = CheckBox(label="calibration hull", value=True)
        self.allow_unconverged = CheckBox(label="allow an unconverged fit", value=False)
        self.button = PushButton(text="Correct")
        self.save_path = FileEdit(label="save as", mode="w", filter="*.json", value="")
        self.save_button = PushButton(text="Save calibration")
        self.button.changed.connect(self.run)
        self.save_button.changed.connect(self.save)
        widgets = [self.image, self.source, self.file, self.interp, self.show_uncertainty, self.trust_only,
                   self.max_error, self.show_hull, self.allow_unconverged, self.button, self.save_path,
                   self.save_button]  # fmt: skip
        super().__init__(napari_viewer, widgets)

    def _calibrations(self, _w=None):
        seen, out = set(), []
        for layer in self.viewer.layers if hasattr(self, "viewer") else []:
            cal = layer.metadata.get(L.CALIBRATION)
            if cal is not None and id(cal) not in seen:
                seen.add(id(cal))
                out.append((f"{cal.name or 'calibration'}: {len(cal.free)} parameters ({layer.name})", cal))
        return out

    def calibration(self):
        """The chosen calibration: the file when one is given, else the chosen layer's."""
        import oapcal

        path = str(self.file.value or "")
        if path and path != "." and Path(path).is_file():
            return oapcal.load_calibration(path)
        cal = self.source.value
        if cal is None:
            from oapcal.errors import DataError

            raise DataError("no calibration: fit one, open a calibration file, or choose a file")
        return cal

    def run(self, _=None) -> None:
        import oapcal

        layer = self._chosen_image()
        if layer is None:
            return
        cal = self._usable_calibration(layer)
        if cal is None:
            return
        data = layer.data
        spatial = 3 if layer.rgb else 2
        shape = data.shape[data.ndim - spatial : data.ndim - spatial + 2]
        interp = self.interp.value
        want_unc, want_hull = self.show_uncertainty.value, self.show_hull.value
        limit = float(self.max_error.value)
        trust_only = bool(self.trust_only.value)

        def work():
            cmap = oapcal.correction_map(cal, shape, max_error_px=limit if trust_only else None)
            if data.ndim == spatial:
                corrected = oapcal.correct_image(np.asarray(data), cmap, interp)
            else:
                corrected = _lazy_stack(data, cmap, interp, spatial)
            unc = None
            if want_unc and cal.covariance is not None and np.size(cal.covariance):
                from oapcal.uncertainty import uncertainty_map

                unc = uncertainty_map(cal, shape, step=UNCERTAINTY_STEP)
            return corrected, unc

        def done(out):
            corrected, unc = out
            _replace_layer(self.viewer, (corrected, {"name": f"{layer.name} corrected", "rgb": layer.rgb,
                                                     "colormap": None if layer.rgb else layer.colormap.name,
                                                     "contrast_limits": layer.contrast_limits,
                                                     "metadata": {L.CALIBRATION: cal}}, "image"))  # fmt: skip
            if unc is not None:
                self._show_uncertainty(unc, cal, limit)
            if want_hull:
                hull = L.hull_layer(cal)
                if hull is not None:
                    _replace_layer(self.viewer, hull)
            lazy = " (lazy: frames are corrected when shown)" if data.ndim > spatial else ""
            self._set_status(f"corrected {layer.name}{lazy}{_trust_status(unc, limit, trust_only)}")

        self._run("correct", work, done)

    def _usable_calibration(self, layer):
        """The chosen calibration when it can correct ``layer`` (converged, or allowed
        unconverged; for its image size); else None, having said why."""
        try:
            cal = self.calibration()
        except Exception as exc:
            self._fail(_message(exc))
            return None
        if not cal.fit.converged and not self.allow_unconverged.value:
            self._fail(f"the calibration's fit did not converge ({cal.fit.message}): refit it, or tick "
                       "'allow an unconverged fit' to use it anyway")  # fmt: skip
            return None
        data = layer.data
        spatial = 3 if layer.rgb else 2
        shape = data.shape[data.ndim - spatial : data.ndim - spatial + 2]
        if cal.image_size and tuple(cal.image_size) != ImageSize.of(shape):  # as 'oapcal correct'
            self._fail(f"{layer.name} is {shape[1]}x{shape[0]} px but the calibration is for "
                       f"{cal.image_size[0]}x{cal.image_size[1]} px images: choose an image of that "
                       "camera, or refit the calibration for this one")  # fmt: skip
            return None
        return cal

    def _show_uncertainty(self, unc, cal, limit: float) -> None:
        """The uncertainty, predicted error and trust region layers of ``unc``."""
        sigma = unc.sigma_px if unc.um_per_px is None else unc.sigma_um
        unit = "px" if unc.um_per_px is None else "um"
        kwargs = {"name": f"uncertainty ({unit})", "colormap": "magma", "opacity": 0.6,
                  "blending": "additive", "scale": (UNCERTAINTY_STEP, UNCERTAINTY_STEP),
                  "metadata": {L.CALIBRATION: cal, "summary": unc.summary()}}  # fmt: skip
        _replace_layer(self.viewer, (sigma.astype(np.float32), kwargs, "image"))
        pred = unc.predicted_px if unc.um_per_px is None else unc.predicted_px * unc.um_per_px
        kwargs = {
            **kwargs,
            "name": f"predicted error ({unit})",
            "colormap": "viridis",
            "visible": False,
        }
        _replace_layer(self.viewer, (pred.astype(np.float32), kwargs, "image"))
        trusted = unc.trusted(limit).astype(np.uint8)
        region = {
            "name": f"trust region (<= {limit:g} px)",
            "opacity": 0.25,
            "scale": (UNCERTAINTY_STEP, UNCERTAINTY_STEP),
            "metadata": {L.CALIBRATION: cal},
        }
        _replace_layer(self.viewer, (trusted, region, "labels"))

    def save(self, _=None) -> None:
        """Save the chosen calibration to ``save as`` (atomically): only to a ``.json`` name,
        never over a file the calibration was read or fitted from, nor over the source file of
        any layer in the viewer (an image open there, say)."""
        import oapcal

        path = str(self.save_path.value or "")
        if not path or path == "." or Path(path).is_dir():
            self._fail("choose a file name to save the calibration as")
            return
        try:
            cal = self.calibration()
            problem = _save_target_problem(path, self._protected_paths(cal))
            if problem:
                self._fail(problem)
                return
            oapcal.save_calibration(cal, path)
        except Exception as exc:
            self._fail(_message(exc))
            return
        self._set_status(f"saved the calibration to {path}")

    def _protected_paths(self, cal) -> dict[str, str]:
        """Paths that ``save`` must not write, each with why: the calibration's own inputs and
        the source of every layer in the viewer."""
        own = [self.file.value, cal.source] + [
            layer.metadata.get("oapcal_source")
            for layer in self.viewer.layers
            if layer.metadata.get(L.CALIBRATION) is cal
        ]
        out = {}
        for p in own:
            if p:
                out.setdefault(str(p), "is a file the calibration was read or fitted from")
        for layer in self.viewer.layers:
            for p in (getattr(getattr(layer, "source", None), "path", None),
                      layer.metadata.get("oapcal_source")):  # fmt: skip
                if p:
                    out.setdefault(str(p), f"is the source of the layer '{layer.name}'")
        return out


def _save_target_problem(path: str, protected: dict[str, str]) -> str | None:
    """Why ``path`` must not receive a calibration (one line), or None: its suffix is not
    ``.json``, or it is (through links, ``..`` or case) one of ``protected``."""
    import os

    if Path(path).suffix.lower() != ".json":
        return f"{path}: a calibration is saved as a .json file; choose a name ending in .json"
    target = Path(path).resolve()
    for p, why in protected.items():
        if p in ("", "."):
            continue
        other = Path(p).resolve()
        same = other == target
        if not same and target.exists() and other.exists():
            try:
                same = os.path.samefile(target, other)
            except OSError:
                same = False
        if same:
            return f"{path}: {why}; choose another name"
    return None


def _lazy_stack(data, cmap, interp: str, spatial: int):
    """A stack corrected frame by frame when napari shows a frame (a Dask array), or at once
    when Dask is not installed."""
    import oapcal

    lead = data.shape[: data.ndim - spatial]
    frame_shape = tuple(cmap.shape) + tuple(data.shape[data.ndim - spatial + 2 :])
    try:
        import dask.array as da
    except ImportError:
        out = np.empty(lead + frame_shape, data.dtype)
        for idx in np.ndindex(*lead):
            out[idx] = oapcal.correct_image(np.asarray(data[idx]), cmap, interp)
        return out
    stack = (
        data
        if isinstance(data, da.Array)
        else da.from_array(data, chunks=(1,) * len(lead) + data.shape[len(lead) :])
    )
    stack = stack.rechunk((1,) * len(lead) + stack.shape[len(lead) :])

    def correct_block(block):
        frame = oapcal.correct_image(np.asarray(block).reshape(block.shape[len(lead) :]), cmap, interp)
        return frame.reshape((1,) * len(lead) + frame.shape)

    return stack.map_blocks(correct_block, dtype=data.dtype, chunks=(1,) * len(lead) + frame_shape)
