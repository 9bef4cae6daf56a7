"""The exported C header's own reference interpolator (`ripplecal_lut_map<ID>_theta`, service/maps/lut_export.py
export_c) run by gcc: one C main, written once, that reads operating points on stdin and prints the theta the
header's function gives. Tests skip (not fail) where gcc is absent: `needs_gcc`."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

GCC_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror")

needs_gcc = pytest.mark.skipif(
    shutil.which("gcc") is None, reason="gcc is not on PATH: the exported C header cannot be compiled here"
)

# one query per line: torque_nm speed_rpm udc_v with_fill gamma_max_rad; out: theta_cos_rad theta_sin_rad
THETA_MAIN = r"""
#include <stdio.h>
#include "lut.h"

int main(void)
{
    float torque_nm, speed_rpm, udc_v, gamma_max_rad, theta_cos_rad, theta_sin_rad;
    int with_fill;
    while (scanf("%f %f %f %d %f", &torque_nm, &speed_rpm, &udc_v, &with_fill, &gamma_max_rad) == 5) {
        ripplecal_lut_map@ID_theta(torque_nm, speed_rpm, udc_v, with_fill, gamma_max_rad, &theta_cos_rad,
                                   &theta_sin_rad);
        printf("%.9g %.9g\n", theta_cos_rad, theta_sin_rad);
    }
    return 0;
}
"""


def f32(x: float) -> float:
    """x as the float the C function takes (the drive's emulator then interpolates at the same point)."""
    return float(np.float32(x))


def build(tmp_path: Path, sources: dict[str, str], extra_flags: tuple[str, ...] = ()) -> Path:
    """Writes `sources` (file name: text) into tmp_path and links the .c files with gcc (GCC_FLAGS, libm)."""
    for name, text in sources.items():
        (tmp_path / name).write_text(text)
    program = tmp_path / "lut"
    c_files = [str(tmp_path / name) for name in sources if name.endswith(".c")]
    done = subprocess.run(
        ["gcc", *GCC_FLAGS, *extra_flags, "-o", str(program), *c_files, "-lm"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    return program


class HeaderTheta:
    """The header's theta function, compiled once with the flags given."""

    def __init__(self, tmp_path: Path, header: str, map_id: int, extra_flags: tuple[str, ...] = ()):
        self.program = build(
            tmp_path, {"lut.h": header, "main.c": THETA_MAIN.replace("@ID", str(int(map_id)))}, extra_flags
        )

    def theta(
        self, points: list[tuple[float, float, float]], with_fill: bool = True, gamma_max_rad: float = np.inf
    ) -> list[tuple[float, float]]:
        """(theta_cos_rad, theta_sin_rad) at each (torque_nm, speed_rpm, udc_v), as float32 points (f32)."""
        g = "inf" if gamma_max_rad == np.inf else f"{f32(gamma_max_rad):.9g}"
        queries = "".join(f"{f32(t):.9g} {f32(n):.9g} {f32(u):.9g} {int(with_fill)} {g}\n" for t, n, u in points)
        out = subprocess.run([str(self.program)], input=queries, capture_output=True, text=True, check=True).stdout
        lines = out.splitlines()
        assert len(lines) == len(points)
        return [(float(a), float(b)) for a, b in (line.split() for line in lines)]
