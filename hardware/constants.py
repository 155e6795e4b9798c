"""Physical constants shared by the device model, the loop and the scenes."""

# Standard gravity (m/s^2), Drake's MultibodyPlant default: what the controller
# compensates, what the hand carries and what the scene plants apply must agree.
GRAVITY_M_S2 = 9.81
