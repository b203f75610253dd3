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
