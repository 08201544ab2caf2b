"""Scene configs shared by test files (a plain module: pytest collects only test_*.py)."""

#: a 4 x 5 net over one sphere, 3 frames of 16 substeps, one camera at 16 x 16: a fit of it
#: compiles in seconds
TINY_SCENE = """
[net]
rows = 4
cols = 5
width = 0.6
height = 0.45
center = [0.0, 0.8, 0.0]
plane = "xz"

[sim]
dt = 0.0333333333333
num_frames = 3
num_substeps = 16

[[spheres]]
center = [0.0, 0.5, 0.0]
radius = 0.2

[render]
width = 16
height = 16
level = 2

[[cameras]]
eye = [0.0, 1.3, 1.9]
target = [0.0, 0.55, 0.0]

"""
