"""Tests of covtool.io.imu_log: CSV IMU logs (time, Δθ, Δv) and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from covtool.errors import InputError
from covtool.io.imu_log import LOG_COLUMNS, load_imu_log, nominal_period, save_imu_log

HEADER = ",".join(LOG_COLUMNS)


def _write(tmp_path, text, name="log.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    t = 12.5 + 0.0025 * np.arange(1, 401)
    dth = rng.standard_normal((400, 3)) * 1e-5
    dv = rng.standard_normal((400, 3)) * 1e-3
    p = tmp_path / "sub" / "kimu.csv"
    save_imu_log(p, t, dth, dv)
    log = load_imu_log(p)
    assert log.path == str(p)
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.dtheta, dth)
    np.testing.assert_array_equal(log.dv, dv)
    assert log.period == pytest.approx(0.0025, rel=1e-9)


def test_columns_in_any_order_and_spaces(tmp_path):
    cols = list(reversed(LOG_COLUMNS))
    rows = [", ".join(cols)]
    for k in range(3):
        vals = {c: str(k + 1) if c == "t [s]" else f"{0.1 * (j + 1)}" for j, c in enumerate(LOG_COLUMNS)}
        rows.append(", ".join(vals[c] for c in cols))
    log = load_imu_log(_write(tmp_path, "\n".join(rows) + "\n"))
    np.testing.assert_array_equal(log.t, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(log.dtheta[0], [0.2, 0.3, 0.4])
    np.testing.assert_allclose(log.dv[0], [0.5, 0.6, 0.7])


def test_nominal_period_ignores_gaps():
    t = np.concatenate([0.01 * np.arange(1, 50), 0.01 * np.arange(60, 100)])
    assert nominal_period(t) == pytest.approx(0.01)


GOOD = "1,0,0,0,0,0,-0.098\n2,0,0,0,0,0,-0.098\n"


@pytest.mark.parametrize("text, match", [
    ("t [s],dtheta_x [rad],dtheta_y [rad]\n1,2,3\n2,3,4\n", r"log\.csv: missing column 'dtheta_z \[rad\]'"),
    (HEADER + ",temperature [C]\n1,0,0,0,0,0,0,20\n2,0,0,0,0,0,0,20\n",
     r"log\.csv: unknown column 'temperature \[C\]'"),
    (HEADER + ",t [s]\n1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,2\n", r"log\.csv: column 't \[s\]' appears more than once"),
    (HEADER + "\n1,0,0,0,0,0,0\n", r"log\.csv: needs at least 2 data rows, found 1"),
    (HEADER + "\n1,0,0,0,0,0,0\n2,0,,0,0,0,0\n", r"log\.csv: column 'dtheta_y \[rad\]': row 2: is empty"),
    (HEADER + "\n1,0,0,0,0,0,0\n2,0,0,0,abc,0,0\n", r"log\.csv: column 'dv_x \[m/s\]': row 2: 'abc' is not a number"),
    (HEADER + "\n1,0,0,0,0,0,0\n2,0,0,inf,0,0,0\n",
     r"log\.csv: column 'dtheta_z \[rad\]': row 2: 'inf' is not finite"),
    (HEADER + "\n1,0,0,0,0,0,0\n2,0,0,0,0,0,0\n1.5,0,0,0,0,0,0\n",
     r"log\.csv: column 't \[s\]': row 3: time 1\.5 s is not after the previous row's 2 s "
     r"\(time must be strictly increasing\)"),
    (HEADER + "\n1,0,0,0,0,0,0\n1,0,0,0,0,0,0\n",
     r"log\.csv: column 't \[s\]': row 2: time 1 s is not after the previous row's 1 s"),
    ("", r"log\.csv: not a readable CSV file"),
])
def test_bad_logs_name_file_column_row(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        load_imu_log(_write(tmp_path, text))


def test_good_minimal_log(tmp_path):
    log = load_imu_log(_write(tmp_path, HEADER + "\n" + GOOD))
    assert log.t.tolist() == [1.0, 2.0]
    assert log.dv[:, 2].tolist() == [-0.098, -0.098]


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.csv: file not found"):
        load_imu_log(tmp_path / "nope.csv")


def test_save_checks_shapes(tmp_path):
    with pytest.raises(ValueError, match=r"expected t \(K,\), dtheta and dv \(K, 3\)"):
        save_imu_log(tmp_path / "x.csv", [1.0, 2.0], np.zeros((2, 3)), np.zeros((3, 3)))
