"""Tests of covtool.io.imu_log: CSV IMU logs (time, Δθ, Δv) and their errors."""

from __future__ import annotations

import dataclasses
import math

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


# --------------------------------------------------------------------------
# issue 9 case 9 and issue 10 cases 5-6
# --------------------------------------------------------------------------


@pytest.mark.parametrize("text, match", [
    (HEADER + "\n1,0,0,0,0,0,-0.098\n2,0,0,0,0\n3,0,0,0,0,0,-0.098\n",
     r"log\.csv: column 'dv_y \[m/s\]': row 2: missing: the line has 5 of the 7 cells of the header "
     r"\(truncated line\?\)"),
    (HEADER + "\n1,0,0,0,0,0,-0.098\n2,0,0,0,0,0,-0.0", r"log\.csv: row 2: the last line has no line end: the file "
                                                       r"looks truncated"),
    (HEADER + "\n1,0,0,0,0,0,-0.098\n2,0,0,0,0,0,-0.098,7\n", r"log\.csv: row 2: the line has 8 cells, the header has 7"),
    (HEADER + "\n1,0,0,0,0,0,-0.098\n\n3,0,0,0,0,0,-0.098\n", r"log\.csv: row 2: empty line"),
])
def test_truncated_and_malformed_lines(tmp_path, text, match):
    """Before: a last line cut inside its last number ('-0.0') was read as a value."""
    with pytest.raises(InputError, match=match):
        load_imu_log(_write(tmp_path, text))


def test_size_limit(tmp_path):
    p = _write(tmp_path, HEADER + "\n" + GOOD)
    size = p.stat().st_size
    with pytest.raises(InputError, match=rf"log\.csv: the file is {size} bytes, larger than the 100 bytes covtool "
                                         r"reads"):
        load_imu_log(p, max_bytes=100)
    assert load_imu_log(p, max_bytes=size).t.size == 2


def _rest_log(n=500, rate=100.0, f=(0.0, 0.0, -9.8), w=(7e-5, 0.0, -4e-5), path="rest.csv"):
    from covtool.io.imu_log import ImuLog

    h = 1.0 / rate
    t = h * np.arange(1, n + 1)
    return ImuLog(path, t, np.tile(np.array(w) * h, (n, 1)), np.tile(np.array(f) * h, (n, 1)))


def test_check_imu_log_range():
    from covtool.io.imu_log import check_imu_log

    log = _rest_log()
    check_imu_log(log, period=0.01, gyro_range=math.radians(1000.0), accel_range=50 * 9.80665)
    dth = log.dtheta.copy()
    dth[42, 1] = -0.2                                   # 20 rad/s over one 10 ms sample: beyond 1000 deg/s
    bad = dataclasses.replace(log, dtheta=dth)
    bound = 1.1 * math.radians(1000.0) * 0.01           # hand: margin × range × period
    with pytest.raises(InputError, match=rf"rest\.csv: column 'dtheta_y \[rad\]': row 43: -0\.2 rad is beyond what the "
                                         rf"main grade can output \(1\.1 × its rate range 1000 deg/s × 0\.01 s = "
                                         rf"{bound:.6g} rad\)"):
        check_imu_log(bad, period=0.01, gyro_range=math.radians(1000.0), label="main")
    check_imu_log(bad, period=0.01, gyro_range=None)    # no range declared: nothing to check


@pytest.mark.parametrize("f, w, match", [
    ((0.0, 0.0, -8.0), (0.0, 0.0, 0.0), r"columns 'dv_x \[m/s\]'\.\.'dv_z \[m/s\]': rows 1-500: the mean specific "
                                        r"force over the 5 s alignment is 8 m/s², not gravity 9\.8 m/s² within 10 %"),
    ((0.0, 0.0, -9.8), (0.0, 0.02, 0.0), r"columns 'dtheta_x \[rad\]'\.\.'dtheta_z \[rad\]': rows 1-500: the mean "
                                         r"rate over the 5 s alignment is 0\.02 rad/s, more than 0\.01 rad/s at rest"),
])
def test_check_imu_log_at_rest(f, w, match):
    from covtool.io.imu_log import check_imu_log

    check_imu_log(_rest_log(), period=0.01, align_time=5.0, gravity=9.8)
    with pytest.raises(InputError, match=r"rest\.csv: " + match):
        check_imu_log(_rest_log(n=800, f=f, w=w), period=0.01, align_time=5.0, gravity=9.8)
