"""GA fleet dispatch for haul trucks on topological mine maps (seed 004).

Modules: :mod:`~btmission.dispatch.topomap` (maps, Π0), :mod:`~.missions` (missions,
fleet missions, F0), :mod:`~.evaluate` (§4.2, eq. 1-2), :mod:`~.ga` (Alg. 1-3), :mod:`~.static`
(§6.1 batches), :mod:`~.dynamic` (§5 re-planning), :mod:`~.push_and_swap` (the §6.1.1 peer),
:mod:`~.maps` (the Fig. 1 and Fig. 6 maps), :mod:`~.plot` (Fig. 3-style Gantt charts).

Map files (YAML) are read and written at the file layer, :mod:`btmission.spec.topomap`.

Nothing heavy is imported here: numba and matplotlib load only when a kernel or plot is needed.
"""
