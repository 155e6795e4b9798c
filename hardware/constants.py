"""Physical constants shared by the device model, the loop and the scenes."""

# Standard gravity (m/s^2), Drake's MultibodyPlant default: what the controller
# compensates, what the hand carries and what the scene plants apply must agree.
GRAVITY_M_S2 = 9.81

# Event times are float sums of periods and offsets: two within this (s) of each
# other are one instant (0.3 + 0.03 > 0.33 by an ulp).
SAME_INSTANT_S = 1e-9
