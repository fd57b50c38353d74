"""SLAM front end: scans prepared in the body frame (``scan_prep``), the knot mirror (``knots``),
pending scans (``pending``), association (``association``) and tracking (``window_tracker``)
against the map, the plane life cycle (``map_builder``, ``plane_init``, ``planemap``), door and
board edges (``edge_finder``, ``edge_tracker``, ``edges``) and the motion model (``motion_model``).
It talks to the back end through ``ports`` only and does not import it."""
