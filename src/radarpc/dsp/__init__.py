"""radarpc.dsp: CFAR, DDMA consolidation, beamforming, spectral point clouds, density, sparse RD."""
from radarpc.dsp.beamform import BeamformResult, angle_spectrum, beamform_peaks, sector_pool
from radarpc.dsp.cfar import CFARResult, ca_cfar, os_cfar
from radarpc.dsp.ddma import (ENVELOPES, DDMAEnvelope, check_rd, consolidate, ddma_envelope, rd_envelope, replica_bins, resolve_tx0_doppler,
                              rx_magnitude_sum, virtual_snapshots)
from radarpc.dsp.density import density_of_mask, max_density, tau_for_density
from radarpc.dsp.pointcloud import EncodedSet, SpectralPointCloud, SpectralPointCloudConfig
from radarpc.dsp.sparse_rd import sparse_rd, sparse_rd_mask

__all__ = [
    "CFARResult", "ca_cfar", "os_cfar",
    "ENVELOPES", "DDMAEnvelope", "ddma_envelope",
    "check_rd", "rx_magnitude_sum", "consolidate", "rd_envelope", "resolve_tx0_doppler",
    "replica_bins", "virtual_snapshots",
    "angle_spectrum", "BeamformResult", "beamform_peaks", "sector_pool",
    "density_of_mask", "max_density", "tau_for_density",
    "SpectralPointCloudConfig", "SpectralPointCloud", "EncodedSet",
    "sparse_rd_mask", "sparse_rd",
]
