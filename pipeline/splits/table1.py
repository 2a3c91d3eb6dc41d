"""The paper's Table I (Rabiee & Biswas, ICRA 2019): the one home of its numbers, shown by both
dataset cards (simulated set and split dataset) next to the measured rows."""

# (category, terrain, name, duration s, distance m,
# abs rotation deg x 1e3, lin mean, lin std m/s, ang mean, ang std deg/s, slip mean, slip std m/s)
PAPER_TABLE_I = [
    ("train", "tile", "Train1", 384, 463.2, 31.1, 1.30, 0.48, 34.3, 48.6, 0.15, 0.12),
    ("train", "asphalt", "Train2", 355, 417.9, 24.1, 1.31, 0.44, 32.7, 40.1, 0.18, 0.12),
    ("train", "grass", "Train3", 977, 764.1, 64.8, 0.87, 0.25, 33.3, 38.9, 0.13, 0.06),
    ("cv", "tile", "CV1", 2059, 910.3, 117.6, 0.48, 0.48, 29.8, 29.2, 0.11, 0.10),
    ("cv", "asphalt", "CV2", 1083, 459.4, 72.0, 0.47, 0.45, 31.5, 17.2, 0.12, 0.08),
    ("cv", "grass", "CV3", 2127, 771.1, 133.8, 0.40, 0.41, 31.19, 24.9, 0.12, 0.08),
    ("ld", "tile", "LD1", 978, 686.0, 22.5, 0.84, 0.61, 8.0, 14.0, 0.08, 0.10),
    ("ld", "asphalt", "LD2", 906, 1070.8, 17.9, 1.33, 0.48, 9.7, 14.4, 0.07, 0.08),
    ("ld", "grass", "LD3", 685, 561.5, 13.2, 0.88, 0.26, 12.8, 16.5, 0.08, 0.05),
]
