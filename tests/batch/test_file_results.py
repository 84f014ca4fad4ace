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
    assert not result.ok and result.param == "allow_size_mismatch" and result.reason == "refused"
    assert "give allow_size_mismatch=True" in result.message and "--" not in result.message


def test_failures_carry_a_reason_code(tmp_path):
    from oapcal.batch.stack import FAILURE_REASONS

    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    inputs = [str(tmp_path / "missing.png"), str(tmp_path / "notes.txt"), str(tmp_path / "*.tif"),
              str(tmp_path / "empty")]  # fmt: skip
    _, failures, _ = expand_inputs(inputs)
    assert [f.reason for f in failures] == ["not_found", "unsupported", "not_found", "not_found"]
    assert all(f.reason in FAILURE_REASONS for f in failures)
    assert FileResult("a.png", "o/a.png", "corrected").reason == ""


def test_disagreeing_registrations_are_a_reason_not_a_message_text():
    import numpy as np

    from oapcal.imaging.detect.core import Detection, _combine, _full_target

    ids = _full_target().corner_ids[:3]
    xy = np.array([[10.0, 10.0], [20.0, 10.0], [30.0, 10.0]])
    one = Detection(tuple(ids), xy, xy, np.zeros(3), 3, um_per_px=100.0)
    other = Detection(tuple(ids), xy + 50.0, xy + 50.0, np.zeros(3), 3, um_per_px=100.0)  # bars 20 px wide
    det = _combine([one, other])
    assert det.status == 1 and det.reason == "registrations_disagree" and det.ids == ()
    assert _combine([one, one]).reason == ""


def test_progress_is_reported_through_a_callback_for_every_frame_of_every_file(tmp_path):
    import numpy as np

    from oapcal.calibration import calibrate
    from oapcal.io.images import write_image
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=1)
    cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(40, 30))
    write_image(tmp_path / "a.png", np.zeros((30, 40), np.uint8))
    write_image(tmp_path / "b.tif", np.zeros((3, 30, 40), np.uint16), stack=True)
    calls = []
    report = correct_stack(cal, [tmp_path / "a.png", tmp_path / "b.tif"], tmp_path / "o", workers=2,
                           progress=lambda *a: calls.append(a))  # fmt: skip
    assert [r.status for r in report.results] == ["corrected", "corrected"]
    assert calls[0] == (0, 4, "files 0/2") and calls[-1] == (4, 4, "files 2/2")
    assert [c[0] for c in calls] == sorted(c[0] for c in calls)  # frames done never go back
    assert {c[2] for c in calls} == {"files 0/2", "files 1/2", "files 2/2"}
