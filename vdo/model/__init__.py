"""What a lab buys: the camera (pinhole + Brown-Conrady, pose), the rail a camera slides on, the
sensor (EMVA 1288 noise) and the speckle pattern (spectrum, gradient energy) and what an interpolating correlation measures on it."""
