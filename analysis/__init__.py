"""Offline studies of the haptic loop (linearization, stability, passivity): to come."""
