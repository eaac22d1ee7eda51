"""tasks - the arc-welding cell's CHC hierarchy (thesis appendix 2, figure A2.1), a module per task.

Level 1: A1 arc temperature, A2 arc voltage, A3 gas, A4 move to position (T5), A5 electrode speed,
A6 stop/memorize position, A7 linear sensor. Level 2: B1 weld on/off, B2 stop (the assassin's arm),
B3 go home, B4 move 5 mm in direction d, B5 approach target. Level 3: C1 unstick tip, C2 find
start of gap. Level 4: D1 inspect gap, D2 weld gap, D3 the sensory exception task. Level 5: E1 the
assassin and E2 the job. ``common`` holds what they share. The install script that builds the
hierarchy is ``chcos/apps/weld/install.chcos``; :data:`HERE` is this directory (the task path).
"""


from chcos import resources

HERE = resources.path("chcos.apps.weld.tasks")
SCRIPT = HERE.parent / "install.chcos"
