"""A simulated robot that drives for real: map, planner, controller, laser, cameras, battery.

Deterministic for a given seed and stepped by a clock the caller passes (sans-IO: no
asyncio, no clock, no threads), so tests run it faster than real time and the daemon runs it
in real time.
"""
