"""The double integrator with friction: its dynamics (:mod:`.model`), numpy twins (:mod:`.dynamics_np`), MPC task
(:mod:`.task`), simulator world (:mod:`.world`) and registry entry (:mod:`.entry`).
"""
