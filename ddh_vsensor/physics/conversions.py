"""The one place for unit conversions, used where SI physics meets bar, mm, rpm and litres."""

import math

BAR_PA = 1.0e5
LPM_M3S = 1.0e-3 / 60.0          # one litre per minute in m^3/s
MM2_M2 = 1.0e-6
CM3_M3 = 1.0e-6
CST_M2S = 1.0e-6                 # one centistokes (mm^2/s) in m^2/s
RPM_REV_S = 1.0 / 60.0
RPM_RAD_S = 2.0 * math.pi / 60.0   # one rpm in rad/s
KELVIN_OFFSET = 273.15
