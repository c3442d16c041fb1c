"""Simulated e-skin: a physical model of the SingleTact + PVDF skin that runs without hardware.

- :mod:`.eskin`: the physics (silicone, sensors, electronics, noise, spatial response) of N taxels.
- :mod:`.stimuli`: the rig protocols' commanded trajectories and the robot that executes them.
- :mod:`.scene`: the live scripted source (sans-I/O ``SceneSource``) and a real-time pacer.
- :mod:`.simulate`: offline datasets in the recording format (``touchreal simulate``).
- :mod:`.compare`: statistics of the simulator vs the rig-v1 recordings (docs/simulator.md).

Every source yields :class:`~touchreal.sensing.raw.RawChunk` blocks (see also :mod:`.replay`).
See docs/simulator.md.
"""
