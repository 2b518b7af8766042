"""The arms: planar, torque-controlled, one MJCF file each (``<name>.xml`` beside this file).

Link lengths are chosen so that every arm reaches every task's workspace (points at
0.45 to 1.0 from the base, plus the push and drawer handles up to ~1.05):

==================  =====================  =====
arm                 link lengths           reach
==================  =====================  =====
three_link          0.4, 0.4, 0.4          1.20
three_link_short    0.45, 0.35, 0.3        1.10
four_link           0.3, 0.3, 0.3, 0.3     1.20
five_link           0.25 x 5               1.25
==================  =====================  =====
"""

from modnet.specs import RobotSpec

ARMS: dict[str, RobotSpec] = {
    spec.name: spec
    for spec in (
        RobotSpec("three_link", (0.4, 0.4, 0.4)),
        RobotSpec("three_link_short", (0.45, 0.35, 0.3)),
        RobotSpec("four_link", (0.3, 0.3, 0.3, 0.3)),
        RobotSpec("five_link", (0.25, 0.25, 0.25, 0.25, 0.25)),
    )
}
