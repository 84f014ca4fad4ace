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


def _never_blocks(call):
    """``call()`` run in a thread, waited for a minute at most (a FIFO opened for reading
    blocks until a writer comes: the caller then releases it and fails)."""
    import threading

    out = {}
    thread = threading.Thread(target=lambda: out.setdefault("value", call()), daemon=True)
    thread.start()
    thread.join(60)
    return thread, out


def _special_files(tmp_path):
    """Files that are not regular files, under names the readers sniff: a FIFO, a link to
    one, a directory, a character device (through a link), a Unix socket."""
    import os
    import socket

    paths = []
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    paths.append(fifo)
    (tmp_path / "link-to-pipe.json").symlink_to(fifo)
    paths.append(tmp_path / "link-to-pipe.json")
    (tmp_path / "dir.csv").mkdir()
    paths.append(tmp_path / "dir.csv")
    (tmp_path / "null.csv").symlink_to("/dev/zero")
    paths.append(tmp_path / "null.csv")
    sock_path = tmp_path / "s.csv"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    paths.append(sock_path)
    return paths, fifo, sock


def test_sniff_never_opens_a_file_that_is_not_a_regular_file(tmp_path):
    import os

    import pytest

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this system")
    paths, fifo, sock = _special_files(tmp_path)
    try:
        thread, out = _never_blocks(lambda: [sniff(p) for p in paths])
        if thread.is_alive():  # release the blocked open, then fail
            fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
            pytest.fail("sniff blocked on a FIFO")
        assert out["value"] == [""] * len(paths)
    finally:
        sock.close()
