"""Field output for ParaView: a VTX series written from 2 ranks reads back as written."""

import pytest

pytest.importorskip("adios2", reason="reading a series back needs the fields extra (adios2)")


def test_a_series_written_from_two_ranks_reads_back_with_its_values_and_times(mpi, tmp_path):
    series, png = tmp_path / "fields.bp", tmp_path / "w.png"
    result = mpi(2, "tests/mpi_scripts/fem_output.py", str(series), str(png), timeout=120)
    assert "ok: 3 steps of 81 nodes" in result.stderr, result.stderr
    assert (series / "md.idx").exists()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
