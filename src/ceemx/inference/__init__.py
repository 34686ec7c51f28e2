"""State inference at a fixed θ: particle filtering and FFBSi smoothing (EKF filtering next)."""

from .particle import ParticleFilterSolution, ffbsi, particle_filter

__all__ = ["ParticleFilterSolution", "ffbsi", "particle_filter"]
