"""Compensation, relighting and bounce separation: the stored matrices streamed against
images (paper §6, eqs. 44-45; Seitz et al. 2005 for the bounces); files, folders of
frames and videos compensated in one call (:mod:`.files`)."""

from .core import (  # noqa: F401
    CompensationReport,
    PathChoice,
    bounce_shares,
    choose_path,
    compensate,
    first_bounce_from_inverse,
    fluctuation,
    matrix_free_apply,
    relative_error,
    relight,
    scan_line,
    separate_bounces,
)
from ..schedule.stream import stream_matmul  # noqa: F401
from .files import (  # noqa: F401
    FileCompensation,
    FileCompensationReport,
    FileSimulation,
    FileSimulationReport,
    RelightReport,
    compensate_files,
    relight_files,
)
from .simulation import (  # noqa: F401
    Flatness,
    SimulatedFrame,
    Simulation,
    SimulationReport,
    simulate,
    simulate_batches,
    simulation_figures,
)

__all__ = ["compensate", "relight", "separate_bounces", "matrix_free_apply", "choose_path",
           "stream_matmul", "bounce_shares", "relative_error", "fluctuation", "scan_line",
           "first_bounce_from_inverse", "PathChoice", "CompensationReport",
           "simulate", "simulate_batches", "simulation_figures", "Simulation",
           "SimulationReport", "Flatness", "SimulatedFrame", "FileCompensation",
           "FileCompensationReport", "compensate_files", "RelightReport", "relight_files",
           "FileSimulation", "FileSimulationReport"]
