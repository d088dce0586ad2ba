"""`fitmedia slab --json` on the command line."""

from __future__ import annotations

import json

import pytest

from fitmedia.cli import main


@pytest.mark.mitsuba
def test_slab_cli_json_matches_van_de_hulst(capsys):
    """Published reference (van de Hulst 1980 via the MCML manual): albedo 0.9, optical
    thickness 2, g 0.75, n 1: R = 0.09739, T = 0.66096, within 1 % (plus 3 MC errors)."""
    assert main(["slab", "--albedo", "0.9", "--optical-thickness", "2", "--g", "0.75", "--n", "1",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res) == {"R", "T", "R_err", "T_err"}
    assert abs(res["R"] - 0.09739) < 0.01 * 0.09739 + 3 * res["R_err"]
    assert abs(res["T"] - 0.66096) < 0.01 * 0.66096 + 3 * res["T_err"]


def test_slab_cli_rejects_a_bad_albedo(capsys):
    assert main(["slab", "--albedo", "1.5", "--optical-thickness", "1", "--g", "0",
                 "--n", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "albedo" in err[0]
