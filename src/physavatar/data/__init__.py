"""Value objects of what the stages write, each read and written in one place.

- :mod:`.tracked`           ``tracked.npz`` (the tracking stage; also a capture's
                            ``ground_truth/meshes.npz``): :class:`~.tracked.TrackedSequence`
- :mod:`.garment_sequence`  ``garment_sequence.npz`` (``simulate``, or any cloth simulator):
                            :class:`~.garment_sequence.GarmentSequence`
- :mod:`.material`          fit-physics' ``material.json``: :class:`~.material.FittedMaterial`;
                            "a preset name or a material .json": :func:`~.material.resolve_material`
- :mod:`.animated`          an ``animate`` folder (``sequence.npz`` + ``sequence.json``):
                            :class:`~.animated.AnimatedSequence`

Each has ``load(path)`` (bad input raises :class:`~physavatar.errors.PhysavatarError` naming the
file and the problem), ``validate()`` and an atomic ``save(path)``. This floor sits above
``sim``/``render``/``splat`` and below ``stages``: it imports neither ``stages`` nor ``cli``.
Import from the modules (``from physavatar.data.tracked import TrackedSequence``): the material
module pulls in the simulator, the others only numpy.
"""
