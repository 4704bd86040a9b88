"""Exploring selpath's cubes: the ``.selpath`` xarray accessor (:mod:`selpath.explore.accessor`, registered by
``import selpath``) and its figures (:mod:`selpath.explore.plots`). Everything here reads; nothing writes a store.
"""
