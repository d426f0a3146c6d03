"""Stateless polarization maths on torch tensors (CPU and CUDA): Stokes, AoLP/DoLP, sensor
mosaics (and telling mono from colour ones, ``optics.pattern``), Fresnel DoLP, the normal <->
azimuth conventions and single-view normals from AoLP and DoLP (``optics.single_view``). Imports
nothing else of the package except ``io.PolarInputError`` and ``threads.numba_scheduling``."""

from polargs_plugin.optics.azimuth import (
    AZIMUTH_MODELS,
    DIFFUSE_AOLP_OFFSET,
    SPECULAR_AOLP_OFFSET,
    aolp_from_normals,
    aolp_to_clockwise,
    azimuth_candidates,
    dolp_weight,
    normal_azimuth,
    normals_from_azimuth,
    pixel_rays,
    wrap_aolp,
    zenith_from_normals,
)
from polargs_plugin.optics.fresnel import (
    DEFAULT_REFRACTIVE_INDEX,
    dolp_diffuse,
    dolp_diffuse_max,
    dolp_specular,
    dolp_specular_conductor,
    fresnel_reflectance,
    fresnel_reflectance_conductor,
    zenith_from_dolp_diffuse,
)
from polargs_plugin.optics.mosaic import (
    MOSAIC_PATTERNS,
    POLARIZER_LATTICE,
    demosaic_polar,
    stokes_from_raw,
    mosaic_from_intensities,
)
from polargs_plugin.optics.single_view import SingleViewNormals, single_view_normals
from polargs_plugin.optics.stokes import (
    POLARIZER_ANGLES_DEG,
    POLARIZER_ANGLES_RAD,
    aolp_from_stokes,
    dolp_from_stokes,
    imax_imin_from_stokes,
    intensities_from_stokes,
    linear_magnitude,
    stokes_from_intensities,
    wrap_angle,
)

__all__ = [
    "AZIMUTH_MODELS",
    "DIFFUSE_AOLP_OFFSET",
    "SPECULAR_AOLP_OFFSET",
    "aolp_from_normals",
    "aolp_to_clockwise",
    "azimuth_candidates",
    "dolp_weight",
    "normal_azimuth",
    "normals_from_azimuth",
    "pixel_rays",
    "wrap_aolp",
    "zenith_from_normals",
    "DEFAULT_REFRACTIVE_INDEX",
    "dolp_diffuse",
    "dolp_diffuse_max",
    "dolp_specular",
    "dolp_specular_conductor",
    "fresnel_reflectance",
    "fresnel_reflectance_conductor",
    "zenith_from_dolp_diffuse",
    "MOSAIC_PATTERNS",
    "POLARIZER_LATTICE",
    "demosaic_polar",
    "stokes_from_raw",
    "mosaic_from_intensities",
    "SingleViewNormals",
    "single_view_normals",
    "POLARIZER_ANGLES_DEG",
    "POLARIZER_ANGLES_RAD",
    "aolp_from_stokes",
    "dolp_from_stokes",
    "imax_imin_from_stokes",
    "intensities_from_stokes",
    "linear_magnitude",
    "stokes_from_intensities",
    "wrap_angle",
]
