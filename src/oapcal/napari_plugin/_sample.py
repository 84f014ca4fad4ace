"""The plugin's sample image: the demo's camera image (``oapcal demo``, step 3) of USAF-1951
groups 4-5 through the ray-traced relay of setup 1, 640 x 480 px of 4.8 um, blur 0.8 px,
peak SNR 50."""

from __future__ import annotations

#: Settings of the demo image (those of :mod:`oapcal.demo`).
SETUP, PIXEL_UM, IMAGE_SIZE, GROUPS, SIGMA_PX, SNR = 1, 4.8, (640, 480), (4, 5), 0.8, 50


def demo_image(seed: int = 0) -> list[tuple]:
    """``[(image, kwargs)]`` for napari: the simulated camera image, with its truth in the
    metadata (``ids``, ``xy_u``, ``xy_d``, ``visible``, ``um_per_px``)."""
    import oapcal

    field = oapcal.relay_distortion(SETUP, pixel_size_um=PIXEL_UM, image_size=IMAGE_SIZE)
    sim = oapcal.simulate_image(GROUPS, field, sigma_px=SIGMA_PX, snr=SNR, seed=seed)
    truth = {
        "ids": sim.ids,
        "xy_u": sim.xy_u,
        "xy_d": sim.xy_d,
        "visible": sim.visible,
        "um_per_px": PIXEL_UM,
    }
    return [
        (sim.image, {"name": "oapcal demo (USAF 4-5, relay setup 1)", "metadata": {"oapcal_truth": truth}})
    ]
