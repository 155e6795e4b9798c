"""What connects the application to a device: the LCM message types and the checks of
every inbound message, the one-controller lease, and the drivers a lab runs for its coil
outputs and head tracker (optional extras). The device's physics is in the folder above."""
