# skinning sets the OpenMP wait policy before pinocchio (imported by several services) loads libgomp
import skinning  # noqa: F401
