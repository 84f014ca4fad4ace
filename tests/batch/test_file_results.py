"""What a batch reports per input: status, ok, and the parameter a message names."""

from oapcal.batch.stack import FileResult, correct_stack, expand_inputs


def test_ok_is_every_status_but_failed(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    files, failures, _ = expand_inputs([str(tmp_path / "missing.png"), str(tmp_path / "notes.txt")])
    assert files == [] and [f.ok for f in failures] == [False, False]
    assert FileResult("a.png", "o/a.png", "skipped").ok and FileResult("a.png", "o/a.png", "corrected").ok


def test_a_size_mismatch_names_its_parameter(tmp_path):
    import numpy as np

    from oapcal.calibration import calibrate
    from oapcal.io.images import write_image
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=1)
    cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(64, 48))
    write_image(tmp_path / "a.png", np.zeros((30, 40), np.uint8))
    report = correct_stack(cal, [tmp_path / "a.png"], tmp_path / "o")
    (result,) = report.results
    assert not result.ok and result.param == "allow_size_mismatch"
    assert "give allow_size_mismatch=True" in result.message and "--" not in result.message
