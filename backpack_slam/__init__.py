"""backpack-slam wiring: the shared configuration loader and rig description (leaf modules that
import nothing else of ours) and the command-line interface (the top layer that wires
segmentation, simulation, slam and calibration together)."""
