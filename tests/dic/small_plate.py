"""The `[defaults]` of the validation files the dic tests write: a 6 x 5 mm patch on a small plate,
0.35 mm dots, a 120 x 90 pixel sensor 0.5 m away (a case renders in about a second)."""

DEFAULTS = """
[defaults]
patch_mm = [6, 5]
plate_margin_mm = 4
dot_mm = 0.35
texel_mm = 0.0125
tile_texels = 1024
edge_blur_mm = 0.06
focal_mm = 25
pixel_um = 5
pixels = [120, 90]
distance_mm = 500
spp = 64
displacement_um = [31, -23, 37]
"""
