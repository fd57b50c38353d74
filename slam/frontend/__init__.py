"""SLAM front end: segments in the body frame, line-to-plane association, plane creation and merging."""
