"""The simulated e-skin: a physical model of the SingleTact + PVDF skin that runs without hardware.

- :mod:`.eskin`: the physics (silicone, sensors, electronics, noise, spatial response) of N taxels.
- :mod:`.stimuli`: the rig protocols' commanded trajectories and the robot that executes them.
- :mod:`.scene`: the live scripted source (sans-I/O ``SceneSource``) and a real-time pacer.
- :mod:`.build`: sensor builds (gains, couplings, noise) the simulator can stand in for.
- :mod:`.simulate`: offline datasets in the recording format (``touchreal simulate``).

Every source yields :class:`~touchreal.raw.RawChunk` blocks. See docs/simulator.md.
"""
