"""The ground floor: configuration loading, the rig schema, rotations, atomic files and JSON.

Imports nothing of ours; every other package may import it.
"""
