"""3-D models of the plate (``doefab mesh``).

- ``build``: :func:`build_meshes`, every model of a fab package's tile
- ``checks``: the formats and the size limits refused before building
- ``relief``: watertight height-field tile mesh, instancing, volume
- ``formats``: PLY, GLB, 3MF, STL encoders (instanced aperture scenes)
- ``step``: the tile as one closed STEP solid, the aperture as an assembly
"""
