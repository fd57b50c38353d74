"""The continuous-time trajectory: interpolation between knots, placement of body points in the
world, the gyro's deskew between knots, and their compiled kernels. Shared by the front end and
the back end."""
