"""The paddle ball: its dynamics (:mod:`.model`), numpy twins (:mod:`.dynamics_np`), one-shot planner (:mod:`.mpc`),
MuJoCo world (:mod:`.world`, :mod:`.bounces`), simulator core (:mod:`.sim`) and registry entry (:mod:`.entry`).
"""
