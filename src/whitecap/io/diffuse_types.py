"""The diffuse particle types: the codes of a diffuse frame's ``type`` array.

Part of the output contract (README, "foam"): every stage that writes, counts,
draws, exports or renders diffuse particles takes the codes and names from
here. Ihmsen et al. 2012 classify by fluid-neighbour count: spray (few),
foam (some), air bubbles (many).
"""

SPRAY, FOAM, BUBBLE = 0, 1, 2
# One particle's type, by code: labels and file names (``diffuse_bubble.pvd``).
TYPE_NAMES = ("spray", "foam", "bubble")
# How many of each, by code: ``counts.csv`` columns, summaries, the Blender objects.
COUNT_NAMES = ("spray", "foam", "bubbles")
# Sphere radius range [min, max] of each type, by code, in fluid particle radii r, where
# [render] sets none: spray small droplets, foam many small bubbles (not cotton balls),
# air bubbles in between. A particle's radius within its range is drawn from its id, so it
# keeps its size from frame to frame. The renderer, the USD/Alembic export and the Blender
# add-on all draw diffuse particles at these sizes.
DIFFUSE_RADIUS = ((0.1, 0.25), (0.15, 0.35), (0.1, 0.3))
