"""Instruments: device protocols, serial drivers, the simulated rig (``devices.sim``) and acquisition sweeps."""
