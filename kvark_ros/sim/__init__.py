"""Simulated robot (MuJoCo plant, pinocchio nominal model) that records bags with ground truth.

Modules: ``plant`` (plant files; no MuJoCo needed, so observers may import it),
``mujoco_plant`` (the MuJoCo model), ``controllers``, ``excitation`` (paper eqs. 24-25),
``scenarios`` (``simulate``/``run_scenario``) and ``cli`` (``kvark simulate``).
"""
