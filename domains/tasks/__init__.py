"""The tasks, one small module (+ scene MJCF) per family, dm_control-suite style."""

from modnet.specs import TaskDefinition

from . import drawer, peg, push, reach, reach_color

TASKS: dict[str, TaskDefinition] = {
    **reach_color.TASKS,
    **reach.TASKS,
    **push.TASKS,
    **peg.TASKS,
    **drawer.TASKS,
}
