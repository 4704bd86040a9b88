"""Simulators shipped with the package: closed-form and Monte Carlo models behind the simulated rig."""
