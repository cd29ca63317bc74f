/* One DDH unit's discrete-time dynamics: one backward-Euler step of motor, pumps, chambers,
 * valves, rod and load, the pumps' delivery at the step's mean speed (the equations, the
 * discrete states and each effect's law are in unit.py's docstring). One row is one unit;
 * ddh_step_rows runs a batch.
 *
 * Each struct's fields are listed once, in an X-macro that declares the struct and fills its
 * field table (name, offset, size), which the Python binding checks its ctypes mirror against
 * before it calls anything.
 */
#include <math.h>
#include <stddef.h>

/* friction states */
enum { F_DOWN = -1, F_STUCK = 0, F_UP = 1, F_IMPACT = 2 };
/* motor states */
enum { M_LIM_NEG = -2, M_NEG = -1, M_STUCK = 0, M_POS = 1, M_LIM_POS = 2, M_SPEED = 3 };

#define MAX_ITERATIONS 16
#define AIR_PASSES 8                /* secant bulk-modulus updates per step at most (with air) */
#define AIR_TOLERANCE_PA 1.0        /* ... until the pressures move less than this between them */
#define AIR_SPLITS 4                /* ... else the step is halved, at most this many times */
#define ORIFICE_LAMINAR_PA 1.0e5    /* below this an orifice leak path flows laminar (linear) */
#define ATMOSPHERE_PA 101325.0      /* physics/air.py's mixture law */
#define POLYTROPIC_EXPONENT 1.4
#define MIN_ABSOLUTE_PA 1000.0      /* below it the gas fills a cavity (deep cavitation) */
#define STORED_ITERATIONS 60        /* ddh_pressure_pa's Newton steps at most */
#define STORED_TOLERANCE_PA 1e-6    /* ... until the stored oil is this close (Pa) */
#define RPM_RAD_S (2.0 * 3.141592653589793 / 60.0)

/* One row's constants. Valve tables per regime (0 anti-cavitation open, 1 closed below the
 * reservoir's pressure, 2 closed above, 3 relief open): conductance g and g x the pressure
 * where the flow is zero. Torque gains [direction: negative, standstill, positive][regime]. */
#define DDH_PARAMS(F)                                                                        \
    F(double, area_a_m2, )                                                                   \
    F(double, area_b_m2, )                                                                   \
    F(double, stroke_m, )                                                                    \
    F(double, dead_volume_m3, )           /* per side */                                     \
    F(double, mass_kg, )                                                                     \
    F(double, load_n, )                                                                      \
    F(double, static_friction_n, )                                                           \
    F(double, coulomb_friction_n, )                                                          \
    F(double, viscous_friction_n_s_m, )                                                      \
    F(double, inertia_kg_m2, )                                                               \
    F(double, torque_limit_nm, )                                                             \
    F(double, speed_limit_rpm, )                                                             \
    F(double, reservoir_pa, )                                                                \
    F(double, bulk_modulus_pa, )                                                             \
    F(double, air_fraction, )             /* free air at atmospheric pressure */            \
    F(double, belt_slip_per_nm, )         /* speed-ratio drop per N*m of |torque| */         \
    F(double, fill_loss, )                /* flow share lost at the speed limit */           \
    F(double, bore_leak_m3_s_pa, )        /* A -> B in the stroke's middle third */          \
    F(double, orifice_leak_a_m3_s_sqrt_pa, )                                                 \
    F(double, orifice_leak_b_m3_s_sqrt_pa, )                                                 \
    F(double, leak_base, )                /* leakage x (base + slope |n|), n motor rpm */    \
    F(double, leak_slope_a_per_rpm, )                                                        \
    F(double, leak_slope_b_per_rpm, )                                                        \
    F(double, seal_friction_a_n_per_pa, )                                                    \
    F(double, seal_friction_b_n_per_pa, )                                                    \
    F(double, hose_compliance_per_pa, )   /* dead volume's wall expansion dV/V per Pa */     \
    F(double, flow_a_m3_s_per_rpm, )      /* pump flow into the chamber per motor rpm */     \
    F(double, flow_b_m3_s_per_rpm, )                                                         \
    F(double, leak_a_m3, )                /* laminar leakage: q = k dp / mu */               \
    F(double, leak_b_m3, )                                                                   \
    F(double, crack_a_pa, )                                                                  \
    F(double, crack_b_pa, )                                                                  \
    F(double, relief_a_pa, )                                                                 \
    F(double, relief_b_pa, )                                                                 \
    F(double, valve_g_a_m3_s_pa, [4])                                                        \
    F(double, valve_ge_a_m3_s, [4])                                                          \
    F(double, valve_g_b_m3_s_pa, [4])                                                        \
    F(double, valve_ge_b_m3_s, [4])                                                          \
    F(double, gain_a_nm_per_pa, [3][4])                                                      \
    F(double, gain_b_nm_per_pa, [3][4])

/* One row's state between steps: pressures over the reservoir, n the motor's rpm, torque the
 * motor's over the last step (belt slip follows it), and the discrete states the next step
 * starts from. */
#define DDH_STATE(F)                                                                         \
    F(double, x_m, )                                                                         \
    F(double, v_m_s, )                                                                       \
    F(double, dp_a_pa, )                                                                     \
    F(double, dp_b_pa, )                                                                     \
    F(double, n_rpm, )                                                                       \
    F(double, torque_nm, )                                                                   \
    F(int, friction_state, )                                                                 \
    F(int, motor_state, )                                                                    \
    F(int, regime_a, )                                                                       \
    F(int, regime_b, )

/* One row's input over a step: in speed mode the motor follows speed_rpm exactly. */
#define DDH_INPUT(F)                                                                         \
    F(double, torque_nm, )                /* commanded, clipped to the limit */              \
    F(double, mu_pa_s, )                  /* the oil's dynamic viscosity */                  \
    F(double, speed_rpm, )                                                                   \
    F(int, speed_controlled, )

#define DDH_COUNTERS(F)                                                                      \
    F(long, iterations, )                 /* linear solves, over all rows and steps */       \
    F(long, unconverged, )                /* row steps whose discrete states did not settle */

#define DECLARE(type, name, dims) type name dims;
struct ddh_params { DDH_PARAMS(DECLARE) };
struct ddh_state { DDH_STATE(DECLARE) };
struct ddh_input { DDH_INPUT(DECLARE) };
struct ddh_counters { DDH_COUNTERS(DECLARE) };

struct ddh_field { const char *name; long offset, size; };
#define PARAMS_FIELD(type, name, dims) \
    { #name, offsetof(struct ddh_params, name), sizeof(((struct ddh_params *)0)->name) },
#define STATE_FIELD(type, name, dims) \
    { #name, offsetof(struct ddh_state, name), sizeof(((struct ddh_state *)0)->name) },
#define INPUT_FIELD(type, name, dims) \
    { #name, offsetof(struct ddh_input, name), sizeof(((struct ddh_input *)0)->name) },
#define COUNTERS_FIELD(type, name, dims) \
    { #name, offsetof(struct ddh_counters, name), sizeof(((struct ddh_counters *)0)->name) },
static const struct ddh_field params_fields[] = { DDH_PARAMS(PARAMS_FIELD) };
static const struct ddh_field state_fields[] = { DDH_STATE(STATE_FIELD) };
static const struct ddh_field input_fields[] = { DDH_INPUT(INPUT_FIELD) };
static const struct ddh_field counters_fields[] = { DDH_COUNTERS(COUNTERS_FIELD) };
#define COUNT(table) ((int)(sizeof(table) / sizeof(table[0])))

/* Field i of struct kind (0 params, 1 state, 2 input, 3 counters): its offset, *name and
 * *size; -1 past the last field or for an unknown kind. */
long ddh_field(int kind, int i, const char **name, long *size)
{
    static const struct ddh_field *const tables[] = {
        params_fields, state_fields, input_fields, counters_fields};
    static const int counts[] = {
        COUNT(params_fields), COUNT(state_fields), COUNT(input_fields), COUNT(counters_fields)};
    if (kind < 0 || kind > 3 || i < 0 || i >= counts[kind])
        return -1;
    *name = tables[kind][i].name;
    *size = tables[kind][i].size;
    return tables[kind][i].offset;
}

/* sizeof the struct of a kind, -1 for an unknown kind */
long ddh_struct_size(int kind)
{
    static const long sizes[] = {sizeof(struct ddh_params), sizeof(struct ddh_state),
                                 sizeof(struct ddh_input), sizeof(struct ddh_counters)};
    return kind < 0 || kind > 3 ? -1 : sizes[kind];
}

/* 0 anti-cavitation open, 1 closed below the reservoir's pressure, 2 above, 3 relief open */
static int regime(double dp, double crack, double relief)
{
    return (dp >= crack) + (dp >= 0.0) + (dp > relief);
}

static int sign(double x) { return (x > 0.0) - (x < 0.0); }

/* physics/air.py: the oil's and the air's share of a unit volume of mixture at a gauge
 * pressure, and the absolute pressure */
static void mixture(const struct ddh_params *p, double dp, double *abs_pa, double *oil,
                    double *air)
{
    double x = p->air_fraction;
    *abs_pa = fmax(dp + p->reservoir_pa + ATMOSPHERE_PA, MIN_ABSOLUTE_PA);
    *oil = (1.0 - x) * exp(-(*abs_pa - ATMOSPHERE_PA) / p->bulk_modulus_pa);
    *air = x * pow(ATMOSPHERE_PA / *abs_pa, 1.0 / POLYTROPIC_EXPONENT);
}

/* 1 / effective bulk modulus of a mixture's shares at its absolute pressure (1/Pa) */
static double mixture_compliance(const struct ddh_params *p, double abs_pa, double oil,
                                 double air)
{
    return (oil / p->bulk_modulus_pa + air / (POLYTROPIC_EXPONENT * abs_pa)) / (oil + air);
}

/* 1 / effective bulk modulus at a gauge pressure (1/Pa) */
static double compliance(const struct ddh_params *p, double dp)
{
    double abs_pa, oil, air;
    mixture(p, dp, &abs_pa, &oil, &air);
    return mixture_compliance(p, abs_pa, oil, air);
}

/* -ln of the mixture's specific volume; below the floor the cavity grows at the floor's
 * compliance (the law's derivative stays its compliance, the pressure barely moves) */
static double log_density(const struct ddh_params *p, double dp)
{
    double abs_pa, oil, air;
    mixture(p, dp, &abs_pa, &oil, &air);
    const double below = dp + p->reservoir_pa + ATMOSPHERE_PA - MIN_ABSOLUTE_PA;
    return -log(oil + air) + (below < 0.0 ? mixture_compliance(p, abs_pa, oil, air) * below
                                          : 0.0);
}

/* mean compliance over [p0, p1]: the exact compression between the two pressures (ld0:
 * log_density at p0, the step's start, computed once a step) */
static double secant_compliance(const struct ddh_params *p, double p0, double ld0, double p1)
{
    double dp = p1 - p0;
    if (fabs(dp) < 100.0)
        return compliance(p, 0.5 * (p0 + p1));
    return (log_density(p, p1) - ld0) / dp;
}

/* The oil a chamber of volume_m3 takes in per pascal at gauge pressure dp (m^3/Pa): the oil's
 * (and its entrained air's) compression and the hoses' walls. */
double ddh_chamber_compliance(const struct ddh_params *p, double volume_m3, double dp)
{
    return volume_m3 * (p->air_fraction > 0.0 ? compliance(p, dp) : 1.0 / p->bulk_modulus_pa)
           + p->dead_volume_m3 * p->hose_compliance_per_pa;
}

/* The oil a chamber holds, as a pressure (Pa): the gauge pressure at which air-free oil would
 * hold as much, beta x the change of -ln V from the reservoir's pressure. Unlike the pressure
 * it measures oil near vacuum too, where a pascal is a share of the chamber. Without air it is
 * the pressure itself. */
double ddh_stored_pa(const struct ddh_params *p, double dp)
{
    if (!(p->air_fraction > 0.0))
        return dp;
    return p->bulk_modulus_pa * (log_density(p, dp) - log_density(p, 0.0));
}

/* d ddh_stored_pa / d dp (>= 1: air only adds compliance) */
double ddh_stored_per_pa(const struct ddh_params *p, double dp)
{
    return p->air_fraction > 0.0 ? p->bulk_modulus_pa * compliance(p, dp) : 1.0;
}

/* The gauge pressure at which a chamber holds stored_pa (ddh_stored_pa's inverse): Newton from
 * guess_pa, bisecting where it leaves the bracket, which is [min(stored, 0), max(stored, 0)]
 * as the slope is at least 1. */
double ddh_pressure_pa(const struct ddh_params *p, double stored_pa, double guess_pa)
{
    if (!(p->air_fraction > 0.0))
        return stored_pa;
    double lo = fmin(stored_pa, 0.0), hi = fmax(stored_pa, 0.0);
    double dp = fmin(fmax(guess_pa, lo), hi);
    for (int it = 0; it < STORED_ITERATIONS; it++) {
        const double f = ddh_stored_pa(p, dp) - stored_pa;
        if (fabs(f) <= STORED_TOLERANCE_PA)
            break;
        if (f > 0.0)
            hi = dp;
        else
            lo = dp;
        const double next = dp - f / ddh_stored_per_pa(p, dp);
        dp = next > lo && next < hi ? next : 0.5 * (lo + hi);
    }
    return dp;
}

/* motor torque per pascal's table row: the direction of turning, or in speed mode of the
 * command */
static int direction(int mm, double speed_rpm)
{
    if (mm == M_SPEED)
        return sign(speed_rpm) + 1;
    return mm < 0 ? 0 : mm == 0 ? 1 : 2;
}

static double pump_torque(const struct ddh_params *p, int d, int ra, int rb, double pa,
                          double pb)
{
    return p->gain_a_nm_per_pa[d][ra] * pa + p->gain_b_nm_per_pa[d][rb] * pb;
}

/* The discrete states and the torque that a state's continuous part implies (a start). */
void ddh_settle(const struct ddh_params *p, struct ddh_state *s, const struct ddh_input *in)
{
    s->x_m = fmin(fmax(s->x_m, 0.0), p->stroke_m);
    s->friction_state = sign(s->v_m_s);
    s->motor_state = in->speed_controlled ? M_SPEED : sign(s->n_rpm);
    s->regime_a = regime(s->dp_a_pa, p->crack_a_pa, p->relief_a_pa);
    s->regime_b = regime(s->dp_b_pa, p->crack_b_pa, p->relief_b_pa);
    s->torque_nm = pump_torque(p, sign(s->n_rpm) + 1, s->regime_a, s->regime_b, s->dp_a_pa,
                               s->dp_b_pa);
}

void ddh_settle_rows(long rows, const struct ddh_params *p, struct ddh_state *s,
                     const struct ddh_input *in)
{
    for (long i = 0; i < rows; i++)
        ddh_settle(p + i, s + i, in + i);
}

/* One step of length h (s). Each element is piecewise linear, so for given discrete states
 * the step is a 2x2 linear solve in (n, v); the states start from the last step's and follow
 * the solution until they are self-consistent. Returns 1 when they are, 0 when
 * MAX_ITERATIONS ran out (the last solution is kept). *air_settled: 0 when the air's secant
 * compression had not settled within AIR_PASSES. */
static int step_once(const struct ddh_params *p, struct ddh_state *s, const struct ddh_input *in,
                     double h, struct ddh_counters *counters, int *air_settled)
{
    const double x = s->x_m, v0 = s->v_m_s, pa0 = s->dp_a_pa, pb0 = s->dp_b_pa;
    const double n0 = s->n_rpm, stroke = p->stroke_m, lim = p->speed_limit_rpm;
    const double area_a = p->area_a_m2, area_b = p->area_b_m2;
    double tau = fmin(fmax(in->torque_nm, -p->torque_limit_nm), p->torque_limit_nm);
    const double va = p->dead_volume_m3 + area_a * x;
    const double vb = p->dead_volume_m3 + area_b * (stroke - x);
    /* leakage conductance x h with its orifice share and speed factor taken at the start */
    const double speed = fabs(n0);
    const double ga = (h * p->leak_a_m3 / in->mu_pa_s + h * p->orifice_leak_a_m3_s_sqrt_pa
                       / sqrt(fmax(fabs(pa0), ORIFICE_LAMINAR_PA)))
                      * (p->leak_base + p->leak_slope_a_per_rpm * speed);
    const double gb = (h * p->leak_b_m3 / in->mu_pa_s + h * p->orifice_leak_b_m3_s_sqrt_pa
                       / sqrt(fmax(fabs(pb0), ORIFICE_LAMINAR_PA)))
                      * (p->leak_base + p->leak_slope_b_per_rpm * speed);
    /* pump flow x h per rpm: belt slip at the last step's torque, fill short at speed */
    const double ratio = fmax(1.0 - p->belt_slip_per_nm * fabs(s->torque_nm), 0.0);
    const double at_limit = n0 / lim;
    const double filled = 1.0 - p->fill_loss * (at_limit * at_limit);
    /* over the step the pumps turn at the mean of its start and end speeds (the trapezoid:
     * the oil delivered is the speed's integral to second order, as the rod's travel) */
    const double qa = 0.5 * h * p->flow_a_m3_s_per_rpm * ratio * filled;
    const double qb = 0.5 * h * p->flow_b_m3_s_per_rpm * ratio * filled;
    /* oil taken in per pascal: the oil's (and air's) compression and the hoses' walls */
    const int has_air = p->air_fraction > 0.0;
    const double hose_c = p->dead_volume_m3 * p->hose_compliance_per_pa;
    double ca = ddh_chamber_compliance(p, va, pa0);
    double cb = ddh_chamber_compliance(p, vb, pb0);
    double gca = ca + ga, gcb = cb + gb;
    /* oil passing a scored piston (m^3), explicit: slow next to the step */
    const double cross = fabs(x / stroke - 0.5) < 1.0 / 6.0
                         ? h * p->bore_leak_m3_s_pa * (pa0 - pb0) : 0.0;
    double cpa = ca * pa0 - cross + qa * n0, cpb = cb * pb0 + cross + qb * n0;
    /* seals pressed by the start pressures */
    const double seal = p->seal_friction_a_n_per_pa * fmax(pa0, 0.0)
                        + p->seal_friction_b_n_per_pa * fmax(pb0, 0.0);
    const double f_coulomb = p->coulomb_friction_n + seal, f_static = p->static_friction_n + seal;
    const double jp = p->inertia_kg_m2 * RPM_RAD_S / h;   /* N*m per rpm of change in a step */
    const double mp = p->mass_kg / h, mpc = mp + p->viscous_friction_n_s_m;
    const double psi = tau + jp * n0;                     /* torque the pump takes at n = 0 */
    const double inertia_force = mp * v0 - p->load_n;     /* force balance at v = 0 */
    const double nha = -h * area_a, hb = h * area_b;
    /* an end stop takes any force */
    const double f_hi = x >= stroke ? INFINITY : f_static, f_lo = x <= 0.0 ? -INFINITY : -f_static;

    int mf = s->friction_state, mm = s->motor_state, ra = s->regime_a, rb = s->regime_b;
    if (in->speed_controlled)
        mm = M_SPEED;
    else if (mm == M_SPEED)
        mm = sign(n0);
    double x_stop = x, v_fix = 0.0, x_new = x, n = n0, v = v0, pa = pa0, pb = pb0;
    int air_passes = has_air ? AIR_PASSES : 0, first_pass = 1, converged = 0;
    double pa_prev = 0.0, pb_prev = 0.0, air_gap = 0.0;
    const double ld_a0 = has_air ? log_density(p, pa0) : 0.0;
    const double ld_b0 = has_air ? log_density(p, pb0) : 0.0;
    for (int it = 0; it < MAX_ITERATIONS; it++) {
        const double den_a = gca + h * p->valve_g_a_m3_s_pa[ra];
        const double den_b = gcb + h * p->valve_g_b_m3_s_pa[rb];
        const double al_a = (cpa + h * p->valve_ge_a_m3_s[ra]) / den_a;
        const double al_b = (cpb + h * p->valve_ge_b_m3_s[rb]) / den_b;
        const double a_a = qa / den_a, a_b = qb / den_b;       /* pressure per rpm */
        const double b_a = nha / den_a, b_b = hb / den_b;      /* pressure per m/s */
        const int d = direction(mm, in->speed_rpm);
        const double k_a = p->gain_a_nm_per_pa[d][ra], k_b = p->gain_b_nm_per_pa[d][rb];
        const int torque_mode = mm * mm == 1, moving = mf * mf == 1;
        double m11, m12, r1, m21, m22, r2;
        if (torque_mode) {
            m11 = jp + k_a * a_a + k_b * a_b;
            m12 = k_a * b_a + k_b * b_b;
            r1 = psi - k_a * al_a - k_b * al_b;
        } else {
            m11 = 1.0;
            m12 = 0.0;
            r1 = mm == M_SPEED ? in->speed_rpm : mm == M_LIM_POS ? lim
                 : mm == M_LIM_NEG ? -lim : 0.0;
        }
        if (moving) {
            m21 = area_b * a_b - area_a * a_a;
            m22 = mpc + area_b * b_b - area_a * b_a;
            r2 = inertia_force - mf * f_coulomb + area_a * al_a - area_b * al_b;
        } else {
            m21 = 0.0;
            m22 = 1.0;
            r2 = v_fix;
        }
        const double det = m11 * m22 - m12 * m21;
        n = (r1 * m22 - m12 * r2) / det;
        v = (m11 * r2 - m21 * r1) / det;
        pa = al_a + a_a * n + b_a * v;
        pb = al_b + a_b * n + b_b * v;
        counters->iterations++;

        /* are the discrete states self-consistent? */
        const int new_ra = regime(pa, p->crack_a_pa, p->relief_a_pa);
        const int new_rb = regime(pb, p->crack_b_pa, p->relief_b_pa);
        x_new = x + h * v;
        const int past_stop = x_new < 0.0 || x_new > stroke;
        const int stuck = mf == F_STUCK;
        const double force0 = stuck ? inertia_force + area_a * pa - area_b * pb : 0.0;
        const int other_motor = mm == M_STUCK || mm == M_LIM_POS || mm == M_LIM_NEG;
        double t_pos = psi, t_neg = psi;
        if (other_motor) {
            t_pos = pump_torque(p, 2, new_ra, new_rb, pa, pb);
            t_neg = pump_torque(p, 0, new_ra, new_rb, pa, pb);
        }
        const int bad = new_ra != ra || new_rb != rb
            || (torque_mode && (mm * n <= 0.0 || fabs(n) > lim))
            || (moving && (mf * v <= 0.0 || past_stop))
            || (stuck && (force0 > f_hi || force0 < f_lo))
            || (mm == M_STUCK && (psi > t_pos || psi < t_neg))
            || (mm == M_LIM_POS && jp * lim + t_pos > psi)
            || (mm == M_LIM_NEG && -jp * lim + t_neg < psi);
        air_gap = first_pass ? INFINITY : fmax(fabs(pa - pa_prev), fabs(pb - pb_prev));
        if (air_passes > 0 && air_gap > AIR_TOLERANCE_PA) {
            /* secant bulk modulus over the step, iterated until the pressures it gives agree
             * with the ones it was taken over: the compression is then exact */
            first_pass = 0;
            pa_prev = pa;
            pb_prev = pb;
            ca = va * secant_compliance(p, pa0, ld_a0, pa) + hose_c;
            cb = vb * secant_compliance(p, pb0, ld_b0, pb) + hose_c;
            gca = ca + ga;
            gcb = cb + gb;
            cpa = ca * pa0 - cross + qa * n0;
            cpb = cb * pb0 + cross + qb * n0;
            air_passes--;
            if (!bad)
                continue;
        }
        if (!bad) {
            converged = 1;
            break;
        }
        /* move to the states the solution implies */
        int new_mf = mf;
        if (moving && mf * v <= 0.0)
            new_mf = F_STUCK;
        else if (moving && past_stop)
            new_mf = F_IMPACT;
        else if (stuck && force0 > f_hi)
            new_mf = F_UP;
        else if (stuck && force0 < f_lo)
            new_mf = F_DOWN;
        /* the stop an impact meets is the nearer end */
        x_stop = new_mf == F_IMPACT ? (x > 0.5 * stroke ? stroke : 0.0) : x;
        v_fix = (x_stop - x) / h;                     /* the velocity that reaches the stop */
        int new_mm = mm;
        if (torque_mode && mm * n <= 0.0)
            new_mm = M_STUCK;
        else if (mm == M_POS && n > lim)
            new_mm = M_LIM_POS;
        else if (mm == M_NEG && n < -lim)
            new_mm = M_LIM_NEG;
        else if (mm == M_STUCK && psi > t_pos)
            new_mm = M_POS;
        else if (mm == M_STUCK && psi < t_neg)
            new_mm = M_NEG;
        else if (mm == M_LIM_POS && jp * lim + t_pos > psi)
            new_mm = M_POS;
        else if (mm == M_LIM_NEG && -jp * lim + t_neg < psi)
            new_mm = M_NEG;
        ra = new_ra;
        rb = new_rb;
        mf = new_mf;
        mm = new_mm;
    }
    if (!converged)
        counters->unconverged++;
    *air_settled = !has_air || air_gap <= AIR_TOLERANCE_PA;

    /* the motor's actual torque: the command, unless the speed is imposed (limit, speed
     * mode): then the one that holds it */
    if (mm == M_LIM_POS || mm == M_LIM_NEG || mm == M_SPEED)
        tau = jp * (n - n0) + pump_torque(p, sign(n) + 1, ra, rb, pa, pb);
    if (mf == F_IMPACT)                              /* an end stop reached exactly */
        x_new = x_stop;
    s->x_m = fmin(fmax(x_new, 0.0), stroke);
    s->v_m_s = v;
    s->dp_a_pa = pa;
    s->dp_b_pa = pb;
    s->n_rpm = n;
    s->torque_nm = tau;
    s->regime_a = ra;
    s->regime_b = rb;
    s->friction_state = mf == F_IMPACT ? F_STUCK : mf;
    s->motor_state = mm;
    return converged;
}

/* One step of length h (s), returning 1 when its discrete states settled. Near vacuum the
 * air's compliance changes by orders of magnitude within a step, and where its secant
 * compression does not settle the step is taken as two halves (down to h / 2^AIR_SPLITS),
 * the speed command of a speed-controlled motor at the halfway point of its ramp. */
static int step_split(const struct ddh_params *p, struct ddh_state *s,
                      const struct ddh_input *in, double h, struct ddh_counters *counters,
                      int splits)
{
    const struct ddh_state start = *s;
    int air_settled;
    const int converged = step_once(p, s, in, h, counters, &air_settled);
    if (air_settled || splits == 0)
        return converged;
    *s = start;
    struct ddh_input half = *in;
    if (in->speed_controlled)
        half.speed_rpm = 0.5 * (start.n_rpm + in->speed_rpm);
    const int first = step_split(p, s, &half, 0.5 * h, counters, splits - 1);
    return step_split(p, s, in, 0.5 * h, counters, splits - 1) && first;
}

int ddh_step(const struct ddh_params *p, struct ddh_state *s, const struct ddh_input *in,
             double h, struct ddh_counters *counters)
{
    if (p->air_fraction > 0.0)
        return step_split(p, s, in, h, counters, AIR_SPLITS);
    int settled;                      /* without air there is no compression to settle */
    return step_once(p, s, in, h, counters, &settled);
}

/* ddh_step over a batch of independent rows; returns how many did not settle */
long ddh_step_rows(long rows, const struct ddh_params *p, struct ddh_state *s,
                   const struct ddh_input *in, double h, struct ddh_counters *counters)
{
    long unsettled = 0;
    for (long i = 0; i < rows; i++)
        unsettled += !ddh_step(p + i, s + i, in + i, h, counters);
    return unsettled;
}
