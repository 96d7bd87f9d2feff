"""Person perception on the robot: laser legs, camera people, tracks (sans-IO)."""
