"""The one module that opens user files (``oapcal.io.userfile``): the sniffing that decides
what a file is reads a bounded head and never raises."""

from __future__ import annotations

from oapcal.io.userfile import sniff


def test_sniff_reads_at_most_the_head_of_a_file_without_line_breaks(tmp_path):
    f = tmp_path / "one-line.csv"
    f.write_bytes(b"x_u," * 250_000)  # 1 MB, no newline
    head = sniff(f, 4096)
    assert len(head) == 4096 and head.startswith("x_u,x_u,")


def test_sniff_gives_nothing_for_binary_data_bad_utf8_and_directories(tmp_path):
    (tmp_path / "a.tif").write_bytes(b"II*\x00" + bytes(100))
    (tmp_path / "latin1.csv").write_bytes(b"x_u,y_u \xe9t\xe9 and more text after it")
    assert sniff(tmp_path / "a.tif") == ""
    assert sniff(tmp_path / "latin1.csv") == ""
    assert sniff(tmp_path) == ""  # a directory: OSError, not raised


def test_sniff_keeps_text_whose_last_character_is_cut_by_the_limit(tmp_path):
    f = tmp_path / "u.csv"
    f.write_text("ab\u00e9cd", encoding="utf-8")  # the e-acute is 2 bytes, at offsets 2-3
    assert sniff(f, 3) == "ab"
    assert sniff(f, 4) == "ab\u00e9"
