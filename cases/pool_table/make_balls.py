"""The pool table's balls: a 15-ball rack (a triangle of touching balls, its apex on the foot spot)
and the cue ball on the head spot, rolling towards the apex. Writes balls.txt beside this script.

    .venv/bin/python cases/pool_table/make_balls.py
"""
from pathlib import Path

import numpy as np

LENGTH, WIDTH = 2.54, 1.27          # playing surface (m)
RADIUS, MASS = 0.028575, 0.17       # a standard ball: 57.15 mm, 170 g
CUE_SPEED = 4.0                     # m/s, a firm break


def balls():
    density = MASS / (4 / 3 * np.pi * RADIUS ** 3)
    apex = np.array([0.75 * LENGTH, WIDTH / 2])
    gap = 1e-5                      # a hair between the racked balls: they touch within the step
    rows = []
    for row in range(5):
        for k in range(row + 1):
            x = apex[0] + row * np.sqrt(3) * (RADIUS + gap / 2)
            y = apex[1] + (k - row / 2) * 2 * (RADIUS + gap / 2)
            rows.append([x, y, RADIUS, 0.0, 0.0, 0.0])
    # the cue ball rolls without sliding: ω = v / r about −y... about y for motion along x
    rows.append([0.25 * LENGTH, WIDTH / 2, RADIUS, CUE_SPEED, 0.0, CUE_SPEED / RADIUS])
    table = np.array([[x, y, z, vx, vy, 0.0, 0.0, wy, 0.0, RADIUS, density] for x, y, z, vx, vy, wy in rows])
    return table


def main():
    path = Path(__file__).with_name("balls.txt")
    np.savetxt(path, balls(), header="x y z vx vy vz wx wy wz radius density", comments="", fmt="%.9g")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
