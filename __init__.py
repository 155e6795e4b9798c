"""maglev-haptics: a co-located magnetic-levitation haptic and 3-D display on Drake."""
