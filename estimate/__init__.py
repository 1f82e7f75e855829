"""Physics: phase functions, Mie reference data, the Mitsuba forward model, the
inverse-rendering optimiser and the mismatch diagnosis. Never imports sim_devices."""
