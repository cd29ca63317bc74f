"""Physics of a DDH unit: SI units inside (m, m^3/s, Pa, N, s); bar, mm, rpm at the edges."""
