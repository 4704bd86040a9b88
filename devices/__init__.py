"""Instruments: device protocols, serial drivers, the simulated rig (``selpath.devices.sim``) and acquisition sweeps."""
