/* The Kalman filter's sample (kalman.py's docstring states its states, equations and noises):
 * a bank of B filters, each predicting with N_ROWS rows of the unit's own dynamics, the
 * code the simulator's plant runs (_unit.c, compiled in here), and updated by the motor's
 * torque. The Hall edges' updates, rare and few, stay in Python between kf_predict_update
 * and kf_finish.
 *
 * Arrays: z (B, n) the states, P (B, n, n) their covariances, prior_var (B, n) the constant
 * parameters' bands (inf elsewhere); the inputs and outputs (N, B) in struct kf_arrays, read
 * and written at sample k. Each struct's fields are listed once, in an X-macro that declares
 * it and fills its field table (name, offset, size, C type), from which the Python binding
 * builds its numpy dtypes.
 */
#include "../model/_unit.c"

enum { X, V, PA, PB, LOAD, DT, EPS, TOFF, COMP, DISP, STICK, N_BASE };
#define N_PLANT 6                   /* states the plant sees (the rest enter linearly) */
#define N_ROWS (N_PLANT + 1)        /* nominal + one per perturbed plant state */
#define KF_MAX_STATES 32           /* 11 + 2 x the switches: ten switches a unit */
#define SQRT_3 1.7320508075688772
#define WALTHER_SHIFT_CST 0.7       /* physics/oil.py */
#define KELVIN_OFFSET 273.15
#define CST_M2S 1.0e-6

/* The bank's settings (KalmanSettings, and what follows from them and the oil). */
#define KF_SETTINGS(F)                                                                       \
    F(double, period_s, )                                                                    \
    F(double, substep_s, )                                                                   \
    F(int, substeps, )                                                                       \
    F(int, nis_window, )                  /* samples */                                      \
    F(int, unexplained_gate, )                                                               \
    F(double, nis_bound, )                /* chi-square of the window at false_alarm */      \
    F(double, torque_gate, )              /* chi-square of one sample at false_alarm */      \
    F(double, deltas, [N_PLANT])          /* finite-difference steps (SI, K) */              \
    F(double, stop_reach, )                                                                  \
    F(double, drive_torque_nm, )                                                             \
    F(double, torque_timing_s, )                                                             \
    F(double, speed_step_rpm, )                                                              \
    F(double, limiter_torque_nm, )                                                           \
    F(double, leak_orifice_share, )                                                          \
    F(double, trapped_share, )                                                               \
    F(double, flow_floor_m3_s, )                                                             \
    F(double, flow_travel_strokes, )                                                         \
    F(double, flow_tau_s, )                                                                  \
    F(double, temp_sd_c, )                                                                   \
    F(double, temp_bound_c, )                                                                \
    F(double, phi_t, )                    /* the oil offset's correlation over a sample */   \
    F(double, load_walk_share, )                                                             \
    F(double, force_noise_n, )                                                               \
    F(double, flow_noise_share, )                                                            \
    F(double, torque_offset_walk_nm, )                                                       \
    F(double, stuck_torque_s, )                                                              \
    F(double, huber, )                                                                       \
    F(double, max_inflation, )                                                               \
    F(double, inflate_per_sample, )                                                          \
    F(double, floor_m, )                                                                     \
    F(double, walther_intercept, )        /* log log (nu + 0.7) = a + b log T */             \
    F(double, walther_slope, )                                                               \
    F(double, density_15c_kg_m3, )                                                           \
    F(double, expansion_per_k, )

/* One filter's unit: what the filter's own equations read of it. */
#define KF_UNIT(F)                                                                           \
    F(double, stroke_m, )                                                                    \
    F(double, inertia_kg_m2, )                                                               \
    F(double, speed_limit_rpm, )                                                             \
    F(double, mass_kg, )                  /* without payload */                              \
    F(double, mass_per_n_kg, )            /* payload mass per N of payload force */          \
    F(double, holding_n, )                /* load force without payload */                   \
    F(double, rated_leak_m3_s, )          /* the larger pump's at 250 bar, 40 degC */        \
    F(double, area_a_m2, )                                                                   \
    F(double, area_b_m2, )                                                                   \
    F(double, dead_m3, )                                                                     \
    F(double, beta_pa, )                                                                     \
    F(double, leak_a_m3, )                                                                   \
    F(double, leak_b_m3, )                                                                   \
    F(double, leak_band_a, )                                                                 \
    F(double, leak_band_b, )                                                                 \
    F(double, orifice_a, )                /* m^3/s/sqrt(Pa), the rating point's leakage */   \
    F(double, orifice_b, )                                                                   \
    F(double, q_per_rpm_a_m3_s, )                                                            \
    F(double, q_per_rpm_b_m3_s, )                                                            \
    F(double, band_half_nm_per_pa, [2])   /* half the pumps' friction band at standstill */  \
    F(double, stored_floor_pa, [2])       /* the oil the valves let a chamber hold (stored) */ \
    F(double, stored_ceiling_pa, [2])

/* One filter's state besides z and P: its discrete modes, its noise scales, what Python's
 * edge updates set (referenced, held: a suspect switch or the edges' CUSUM beyond), and the
 * sample it (re)started at (after a gap the inputs before are not its sample's past). */
#define KF_FILTER(F)                                                                         \
    F(long, since, )                                                                         \
    F(double, load_scale_n, )                                                                \
    F(double, flow_scale, )               /* the flow error's variance over the bands' */    \
    F(double, flow_sigma_m3_s, )                                                             \
    F(double, phi_q, )                                                                       \
    F(int, friction_state, )                                                                 \
    F(int, regime_a, )                                                                       \
    F(int, regime_b, )                                                                       \
    F(int, was_stopped, )                                                                    \
    F(int, referenced, )                                                                     \
    F(int, held, )                                                                           \
    F(double, p_pa, [2])                  /* the chambers' gauge pressures: the oil z holds */

/* The bank's inputs and outputs, (N, B) each (pressures (N, B, 2)); measured: the sample's
 * torque was read (0: a lost frame's, interpolated). */
#define KF_ARRAYS(F)                                                                         \
    F(const unsigned char *, measured, )                                                     \
    F(const double *, speed_rpm, )                                                           \
    F(const double *, torque_nm, )        /* the shaft's, from the drive's reading */        \
    F(const double *, temp_c, )           /* the pumps' oil */                               \
    F(double *, nis, )                                                                       \
    F(double *, nis_window, )                                                                \
    F(double *, x_m, )                                                                       \
    F(double *, v_m_s, )                                                                     \
    F(double *, sd_m, )                                                                      \
    F(double *, load_n, )                                                                    \
    F(double *, temp_offset_c, )                                                             \
    F(double *, torque_offset_nm, )                                                          \
    F(double *, flow_error_m3_s, )                                                           \
    F(double *, flow_sigma_m3_s, )                                                           \
    F(double *, pressures_bar, )                                                             \
    F(unsigned char *, flagged, )                                                            \
    F(unsigned char *, not_referenced, )

struct kf_settings { KF_SETTINGS(DECLARE) };
struct kf_unit { KF_UNIT(DECLARE) };
struct kf_filter { KF_FILTER(DECLARE) };
struct kf_arrays { KF_ARRAYS(DECLARE) };

struct kf_field { const char *name, *type; long offset, size; };
#define SETTINGS_KF(type, name, dims) \
    { #name, #type, offsetof(struct kf_settings, name), sizeof(((struct kf_settings *)0)->name) },
#define UNIT_KF(type, name, dims) \
    { #name, #type, offsetof(struct kf_unit, name), sizeof(((struct kf_unit *)0)->name) },
#define FILTER_KF(type, name, dims) \
    { #name, #type, offsetof(struct kf_filter, name), sizeof(((struct kf_filter *)0)->name) },
#define ARRAYS_KF(type, name, dims) \
    { #name, #type, offsetof(struct kf_arrays, name), sizeof(((struct kf_arrays *)0)->name) },
static const struct kf_field kf_tables[4][40] = {
    {KF_SETTINGS(SETTINGS_KF)}, {KF_UNIT(UNIT_KF)}, {KF_FILTER(FILTER_KF)},
    {KF_ARRAYS(ARRAYS_KF)}};
static const long kf_sizes[4] = {sizeof(struct kf_settings), sizeof(struct kf_unit),
                                 sizeof(struct kf_filter), sizeof(struct kf_arrays)};

/* Field i of struct kind (0 settings, 1 unit, 2 filter, 3 arrays): its offset, *name, *type
 * and *size; -1 past the last field or for an unknown kind. */
long kf_field(int kind, int i, const char **name, const char **type, long *size)
{
    if (kind < 0 || kind > 3 || i < 0 || i >= 40 || kf_tables[kind][i].name == NULL)
        return -1;
    *name = kf_tables[kind][i].name;
    *type = kf_tables[kind][i].type;
    *size = kf_tables[kind][i].size;
    return kf_tables[kind][i].offset;
}

long kf_struct_size(int kind) { return kind < 0 || kind > 3 ? -1 : kf_sizes[kind]; }

long kf_max_states(void) { return KF_MAX_STATES; }

static double clip(double v, double lo, double hi) { return fmin(fmax(v, lo), hi); }

/* physics/oil.py: ASTM D341 (Walther) and linear thermal expansion */
static double viscosity_pa_s(const struct kf_settings *s, double temp_c)
{
    const double t = log10(temp_c + KELVIN_OFFSET);
    const double nu = pow(10.0, pow(10.0, s->walther_intercept + s->walther_slope * t))
                      - WALTHER_SHIFT_CST;
    return nu * CST_M2S * (s->density_15c_kg_m3
                           / (1.0 + s->expansion_per_k * (temp_c - 15.0)));
}

/* The unmodelled flow's stationary standard deviation (m^3/s into chamber A): the pumps'
 * laminar leakage off by each side's band, the share of the rating point's leakage that may
 * pass orifice-like gaps (the orifice law against the laminar one), the trapped volumes'
 * compression, each a bound whose RMS is bound / sqrt(3), and a floor for the seals. */
static double flow_sigma(const struct kf_settings *s, const struct kf_unit *u, double mu,
                         const double *p_pa, double speed_rpm)
{
    const double pa = fabs(p_pa[0]), pb = fabs(p_pa[1]);
    const double leak = (u->leak_band_a * fabs(u->leak_a_m3 * p_pa[0])
                         + u->leak_band_b * fabs(u->leak_b_m3 * p_pa[1])) / mu;
    const double orifice = fabs(u->orifice_a * sqrt(pa) - u->leak_a_m3 * pa / mu)
                           + fabs(u->orifice_b * sqrt(pb) - u->leak_b_m3 * pb / mu);
    const double trapped = s->trapped_share * fabs(speed_rpm)
                           * (u->q_per_rpm_a_m3_s * pa + u->q_per_rpm_b_m3_s * pb) / u->beta_pa;
    return (leak + s->leak_orifice_share * orifice + trapped) / SQRT_3 + s->flow_floor_m3_s;
}

/* What the samples cannot tell about the torque at sample k, the filter's `fresh`-th since
 * its start (>= 1) (N*m^2): the drive's estimate, the reading's timing within its sample,
 * the speed's resolution read as inertia torque, the speed's bend beyond the parabola
 * through three samples, the limiter at the speed limit. */
static double torque_variance(const struct kf_settings *s, const struct kf_unit *u,
                              const struct kf_arrays *a, long B, long b, long k, long fresh)
{
    const double *tq = a->torque_nm, *n = a->speed_rpm;
    const double T = s->period_s;
    double var = s->drive_torque_nm * s->drive_torque_nm;
    const double d_tq = s->torque_timing_s * (tq[k * B + b] - tq[(k - 1) * B + b]) / T;
    var += d_tq * d_tq;
    const double j_per_rpm = u->inertia_kg_m2 * RPM_RAD_S / T;
    var += j_per_rpm * j_per_rpm * (s->speed_step_rpm * s->speed_step_rpm) / 6.0;
    if (fresh >= 2) {
        const double d = 0.5 * j_per_rpm
                         * (n[k * B + b] - 2.0 * n[(k - 1) * B + b] + n[(k - 2) * B + b]);
        var += d * d;
    }
    const double reach = u->speed_limit_rpm - s->speed_step_rpm;
    const int at_limit = fabs(n[k * B + b]) >= reach || fabs(n[(k - 1) * B + b]) >= reach;
    return var + (at_limit ? s->limiter_torque_nm * s->limiter_torque_nm : 0.0);
}

/* One filter from sample k - 1 to k (k past its start): the rows stepped through the sample
 * with the motor following the measured speed, the Jacobian by finite differences, the
 * covariance, and the torque's update. The samples are the drive's, at its fixed period. */
static void predict_update(long B, long n, long k, const struct kf_settings *s,
                           const struct kf_unit *u, struct kf_filter *f, double *z, double *P,
                           double *prior_var, struct ddh_params *rp, struct ddh_state *rs,
                           struct ddh_input *ri, const struct kf_arrays *a, long b,
                           struct ddh_counters *counters)
{
    const double T = s->period_s, stroke = u->stroke_m;
    const double n0 = a->speed_rpm[(k - 1) * B + b], n1 = a->speed_rpm[k * B + b];
    const long fresh = k - f->since;
    const double nm = fresh >= 2 ? a->speed_rpm[(k - 2) * B + b] : 2.0 * n0 - n1;
    const double t_mid = 0.5 * (a->temp_c[(k - 1) * B + b] + a->temp_c[k * B + b]);
    const double x_before = z[X];
    /* the chambers' states are the oil they hold (ddh_stored_pa, the pressure itself without
     * air): the rows start from the pressures holding it (f->p_pa, kept by kf_finish), a
     * perturbed one by that much oil */
    const double per_pa[2] = {ddh_stored_per_pa(rp, f->p_pa[0]),
                              ddh_stored_per_pa(rp, f->p_pa[1])};
    /* x is perturbed away from the nearer stroke end by stop_reach sigma: the slope of a
     * stop's clip over the spread is the share of rods not yet there */
    double deltas[N_PLANT];
    for (int j = 0; j < N_PLANT; j++)
        deltas[j] = s->deltas[j];
    const double away = z[X] > 0.5 * stroke ? -1.0 : 1.0;
    deltas[X] = away * fmin(fmax(s->deltas[X], s->stop_reach * sqrt(fmax(P[X * n + X], 0.0))),
                            0.5 * stroke);
    /* the oil's viscosity, the nominal rows' and the oil offset's perturbed row's */
    const double mu = viscosity_pa_s(s, t_mid + z[DT]);
    const double mu_dt = viscosity_pa_s(s, t_mid + (z[DT] + deltas[DT]));
    for (int j = 0; j < N_ROWS; j++) {
        double row[N_PLANT];
        for (int i = 0; i < N_PLANT; i++)
            row[i] = z[i];
        if (j > 0)
            row[j - 1] += deltas[j - 1];
        struct ddh_params *p = rp + j;
        struct ddh_state *st = rs + j;
        struct ddh_input *in = ri + j;
        st->x_m = clip(row[X], 0.0, stroke);
        st->v_m_s = row[V];
        st->dp_a_pa = j - 1 == PA ? f->p_pa[0] + deltas[PA] / per_pa[0] : f->p_pa[0];
        st->dp_b_pa = j - 1 == PB ? f->p_pa[1] + deltas[PB] / per_pa[1] : f->p_pa[1];
        p->load_n = row[LOAD];
        /* the moving mass follows from the payload the load implies */
        p->mass_kg = u->mass_kg + fmax((row[LOAD] - u->holding_n) * u->mass_per_n_kg, 0.0);
        st->friction_state = f->friction_state;
        st->regime_a = f->regime_a;
        st->regime_b = f->regime_b;
        st->n_rpm = n0;
        in->mu_pa_s = j - 1 == DT ? mu_dt : mu;
        in->torque_nm = 0.0;
        in->speed_controlled = 1;
    }
    /* the motor's speed over the sample: the parabola through the last three samples */
    for (int i = 0; i < s->substeps; i++) {
        const double tau = (double)(i + 1) / (double)s->substeps;
        const double n_tau = n0 + tau * (n1 - nm) / 2.0 + tau * tau * (n1 - 2.0 * n0 + nm) / 2.0;
        for (int j = 0; j < N_ROWS; j++) {
            ri[j].speed_rpm = n_tau;
            ddh_step(rp + j, rs + j, ri + j, s->substep_s, counters);
        }
    }
    const double nom[4] = {rs[0].x_m, rs[0].v_m_s, ddh_stored_pa(rp, rs[0].dp_a_pa),
                           ddh_stored_pa(rp, rs[0].dp_b_pa)};
    double Fp[4][N_PLANT];            /* d(x, v, dp_a, dp_b) / d(plant state) */
    double H[KF_MAX_STATES] = {0.0};
    for (int j = 0; j < N_PLANT; j++) {
        const double out[4] = {rs[j + 1].x_m, rs[j + 1].v_m_s,
                               ddh_stored_pa(rp, rs[j + 1].dp_a_pa),
                               ddh_stored_pa(rp, rs[j + 1].dp_b_pa)};
        for (int i = 0; i < 4; i++)
            Fp[i][j] = (out[i] - nom[i]) / deltas[j];
        H[j] = (rs[j + 1].torque_nm - rs[0].torque_nm) / deltas[j];
    }
    H[TOFF] = 1.0;
    double tq_model = rs[0].torque_nm;
    /* the flow error forgets as the operating point moves, and at a hold over flow_tau_s */
    const double moved = fabs(nom[X] - z[X]) / (s->flow_travel_strokes * stroke);
    f->phi_q = exp(-(T / s->flow_tau_s + moved));
    f->flow_sigma_m3_s = flow_sigma(s, u, mu, f->p_pa, 0.5 * (n0 + n1))
                         * sqrt(f->flow_scale);
    /* the unmodelled flow, the chambers' compliance and the delivered displacement move the
     * rod (against a stroke end the compliance and displacement nothing, the flow as far as
     * the rod floats) */
    const int at_end = nom[X] <= 0.0 || nom[X] >= stroke;
    double floating = !at_end;   /* the odds that the rod floats on the oil, not on a stop */
    const int measured = a->measured[k * B + b];
    const double R = measured ? torque_variance(s, u, a, B, b, k, fresh) : 0.0;
    if (at_end && measured) {
        /* on a stop or short of it: the nominal row is on it (the stop carries the load, the
         * chambers are closed volumes) and the spread's row short of it floats on the oil;
         * the spread closes by the rods on the stop only as far as the torque says the rod
         * is on it (the two rows' torques as the modes' likelihoods, even odds) */
        const double S = R + P[TOFF * n + TOFF];
        const double tq = a->torque_nm[k * B + b] - z[TOFF];
        const double y0 = tq - rs[0].torque_nm, y1 = tq - rs[1].torque_nm;
        const double odds = (y0 * y0 - y1 * y1) / (2.0 * S);
        const double on = isnan(odds) ? 1.0 : 1.0 / (1.0 + exp(odds));
        Fp[X][X] = on * Fp[X][X] + (1.0 - on);
        floating = 1.0 - on;
    }
    /* the unmodelled flow moves a floating rod, one on a stop not at all */
    double gain_x = floating * T * f->flow_sigma_m3_s / u->area_a_m2, comp_x = 0.0, disp_x = 0.0;
    if (!at_end) {
        const double x = clip(z[X], 0.0, stroke);
        const double va = u->dead_m3 + u->area_a_m2 * x;
        const double vb = u->dead_m3 + u->area_b_m2 * (stroke - x);
        const double dva = va * (nom[PA] - z[PA]) / u->beta_pa;
        const double dvb = vb * (nom[PB] - z[PB]) / u->beta_pa;
        comp_x = -0.5 * (dva / u->area_a_m2 - dvb / u->area_b_m2);
        disp_x = nom[X] - z[X];
    }
    /* P <- F P F' + Q; F is the identity but for its first four rows and DT, EPS */
    double diag[KF_MAX_STATES];
    for (long i = 0; i < n; i++)
        diag[i] = 1.0;
    diag[DT] = s->phi_t;
    diag[EPS] = f->phi_q;
    double A[KF_MAX_STATES * KF_MAX_STATES];
    for (long c = 0; c < n; c++) {
        for (int i = 0; i < 4; i++) {
            double acc = 0.0;
            for (int j = 0; j < N_PLANT; j++)
                acc += Fp[i][j] * P[j * n + c];
            if (i == X)
                acc += gain_x * P[EPS * n + c] + comp_x * P[COMP * n + c]
                       + disp_x * P[DISP * n + c];
            A[i * n + c] = acc;
        }
        for (long i = 4; i < n; i++)
            A[i * n + c] = diag[i] * P[i * n + c];
    }
    for (long r = 0; r < n; r++) {
        for (int i = 0; i < 4; i++) {
            double acc = 0.0;
            for (int j = 0; j < N_PLANT; j++)
                acc += A[r * n + j] * Fp[i][j];
            if (i == X)
                acc += A[r * n + EPS] * gain_x + A[r * n + COMP] * comp_x
                       + A[r * n + DISP] * disp_x;
            P[r * n + i] = acc;
        }
        for (long i = 4; i < n; i++)
            P[r * n + i] = A[r * n + i] * diag[i];
    }
    /* process noise: a white force, white flows, the load's and the torque offset's walks,
     * the oil offset's and the flow error's Gauss-Markov; a stuck motor's torque moves
     * within its band as the drive's controller winds */
    const double cap = (u->dead_m3 + u->area_a_m2 * 0.5 * stroke) / u->beta_pa;
    const double fv = s->force_noise_n / u->mass_kg, fp = s->flow_noise_share
                      * u->rated_leak_m3_s / cap, fl = s->load_walk_share * f->load_scale_n;
    P[V * n + V] += fv * fv * T;
    P[PA * n + PA] += fp * fp * T;
    P[PB * n + PB] += fp * fp * T;
    P[LOAD * n + LOAD] += fl * fl * T;
    P[DT * n + DT] += s->temp_sd_c * s->temp_sd_c * (1.0 - s->phi_t * s->phi_t);
    P[EPS * n + EPS] += 1.0 - f->phi_q * f->phi_q;
    P[TOFF * n + TOFF] += s->torque_offset_walk_nm * s->torque_offset_walk_nm * T;
    P[STICK * n + STICK] += (f->was_stopped ? prior_var[STICK] : 0.0) * T / s->stuck_torque_s;
    /* the states through the sample */
    const double z_eps = z[EPS], z_comp = z[COMP], z_disp = z[DISP];
    for (int i = 0; i < 4; i++)
        z[i] = nom[i];
    z[X] += gain_x * z_eps + comp_x * z_comp + disp_x * z_disp;
    z[DT] *= s->phi_t;
    z[EPS] *= f->phi_q;
    f->p_pa[0] = rs[0].dp_a_pa;
    f->p_pa[1] = rs[0].dp_b_pa;
    f->friction_state = rs[0].friction_state;
    f->regime_a = rs[0].regime_a;
    f->regime_b = rs[0].regime_b;
    if (fresh > 1) {
        /* fading memory by the window's excess; a constant parameter is never less known
         * than its band says (scaled as D P D, P stays PSD) */
        const double ratio = a->nis_window[(k - 1) * B + b];
        const double grow = ratio > 1.0
                            ? pow(fmin(ratio, s->max_inflation), s->inflate_per_sample) : 1.0;
        double d[KF_MAX_STATES];
        if (grow != 1.0) {
            for (long i = 0; i < n; i++) {
                for (long c = 0; c < n; c++)
                    P[i * n + c] *= grow;
            }
        }
        int bounded = 0;
        for (long i = 0; i < n; i++) {
            d[i] = sqrt(fmin(1.0, prior_var[i] / fmax(P[i * n + i], 1e-300)));
            bounded |= d[i] < 1.0;
        }
        if (bounded) {
            for (long i = 0; i < n; i++) {
                for (long c = 0; c < n; c++)
                    P[i * n + c] = d[i] * P[i * n + c] * d[c];
            }
        }
    }
    /* the torque's update; a frame the bus lost (its inputs interpolated) measures nothing */
    if (!measured) {
        a->nis[k * B + b] = 0.0;
        return;
    }
    /* a motor standing still is held by the pumps' friction: any torque within the band
     * holds the pressures, one value for the stop (a state drawn anew as the motor stops) */
    const int stopped = fabs(a->speed_rpm[k * B + b]) < 0.5 * s->speed_step_rpm;
    if (stopped) {
        const double h0 = u->band_half_nm_per_pa[0], h1 = u->band_half_nm_per_pa[1];
        tq_model = tq_model - h0 * f->p_pa[0] - h1 * f->p_pa[1];
        H[PA] -= h0 / ddh_stored_per_pa(rp, f->p_pa[0]);
        H[PB] -= h1 / ddh_stored_per_pa(rp, f->p_pa[1]);
        if (!f->was_stopped) {
            const double w = fabs(h0 * f->p_pa[0]) + fabs(h1 * f->p_pa[1]);
            const double band_var = w * w / 3.0;
            z[STICK] = 0.0;
            for (long i = 0; i < n; i++)
                P[STICK * n + i] = P[i * n + STICK] = 0.0;
            P[STICK * n + STICK] = band_var;
            prior_var[STICK] = band_var;
        }
        H[STICK] = 1.0;
    }
    f->was_stopped = stopped;
    const double y = a->torque_nm[k * B + b]
                     - (tq_model + z[TOFF] + (stopped ? z[STICK] : 0.0));
    double PH[KF_MAX_STATES], K[KF_MAX_STATES];
    double hph = 0.0;
    for (long i = 0; i < n; i++) {
        double acc = 0.0;
        for (long j = 0; j < n; j++)
            acc += P[i * n + j] * H[j];
        PH[i] = acc;
    }
    for (long i = 0; i < n; i++)
        hph += H[i] * PH[i];
    /* never below the measurement's own variance */
    double S = fmax(hph, 0.0) + R;
    const double nis = y * y / S;
    a->nis[k * B + b] = nis;
    /* Huber: an innovation beyond huber sigma moves the states by at most that */
    S = S * fmax(1.0, sqrt(nis) / s->huber);
    for (long i = 0; i < n; i++)
        K[i] = PH[i] / S;
    if (s->unexplained_gate && nis > s->torque_gate) {
        /* a torque the model cannot explain leaves the slow states, and the travel the model
         * predicted over the sample is not known to have happened */
        K[LOAD] = K[DT] = K[TOFF] = 0.0;
        const double moved_x = z[X] - x_before;
        P[X * n + X] += moved_x * moved_x;
    }
    /* what is position is considered (Schmidt), not updated */
    K[X] = K[EPS] = K[DISP] = 0.0;
    for (long i = N_BASE; i < n; i++)
        K[i] = 0.0;
    for (long i = 0; i < n; i++)
        z[i] += K[i] * y;
    for (int c = 0; c < 2; c++)
        z[PA + c] = clip(z[PA + c], u->stored_floor_pa[c], u->stored_ceiling_pa[c]);
    /* Joseph's form for that gain */
    for (long i = 0; i < n; i++) {
        for (long j = 0; j < n; j++)
            P[i * n + j] = P[i * n + j] - K[i] * PH[j] - K[j] * PH[i] + K[i] * (S * K[j]);
    }
}

/* Sample k of every filter up to its edges: the prediction from k - 1 and the torque's update
 * (k past the filter's start), the position clipped to the stroke. rows: the plant's
 * B * N_ROWS rows. Returns the row steps whose discrete states did not settle. */
long kf_predict_update(long B, long n, long k, const struct kf_settings *s,
                       const struct kf_unit *units, struct kf_filter *filters, double *z,
                       double *P, double *prior_var, struct ddh_params *rp,
                       struct ddh_state *rs, struct ddh_input *ri,
                       const struct kf_arrays *a, struct ddh_counters *counters)
{
    long before = counters->unconverged;
    for (long b = 0; b < B; b++) {
        if (k > filters[b].since)
            predict_update(B, n, k, s, units + b, filters + b, z + b * n, P + b * n * n,
                           prior_var + b * n, rp + b * N_ROWS, rs + b * N_ROWS,
                           ri + b * N_ROWS, a, b, counters);
        z[b * n + X] = clip(z[b * n + X], 0.0, units[b].stroke_m);
    }
    return counters->unconverged - before;
}

/* Sample k's end, after its edges: the bounds, the covariance kept symmetric and its variances
 * non-negative, the self-check's window and the outputs. Returns 0, or 1 + the first filter
 * whose state is not finite. */
long kf_finish(long B, long n, long k, const struct kf_settings *s,
               const struct kf_unit *units, struct kf_filter *filters, double *Z,
               double *PP, const struct ddh_params *rp, const struct kf_arrays *a)
{
    long bad = 0;
    for (long b = 0; b < B; b++) {
        struct kf_filter *f = filters + b;
        double *z = Z + b * n, *P = PP + b * n * n;
        z[DT] = clip(z[DT], -s->temp_bound_c, s->temp_bound_c);
        z[X] = clip(z[X], 0.0, units[b].stroke_m);
        P[X * n + X] = fmax(P[X * n + X], s->floor_m * s->floor_m);
        /* the rod is within its stroke: no spread beyond half of it (a variable bounded to
         * [0, L] has a variance of at most L^2 / 4); scaled as D P D, P stays PSD */
        const double var_max = 0.25 * units[b].stroke_m * units[b].stroke_m;
        if (P[X * n + X] > var_max) {
            const double scale = sqrt(var_max / P[X * n + X]);
            for (long i = 0; i < n; i++) {
                P[X * n + i] *= scale;
                P[i * n + X] *= scale;
            }
        }
        int finite = 1;
        for (long i = 0; i < n; i++) {
            for (long j = i; j < n; j++) {
                const double m = 0.5 * (P[i * n + j] + P[j * n + i]);
                P[i * n + j] = P[j * n + i] = m;
            }
            P[i * n + i] = fmax(P[i * n + i], 0.0);
            finite &= isfinite(z[i]);
            for (long j = 0; j < n; j++)
                finite &= isfinite(P[i * n + j]);
        }
        if (!finite && !bad)
            bad = b + 1;
        double sum = 0.0;
        for (long i = k - s->nis_window + 1 > 0 ? k - s->nis_window + 1 : 0; i <= k; i++)
            sum += a->nis[i * B + b];
        const long o = k * B + b;
        a->nis_window[o] = sum / s->nis_bound;
        a->flagged[o] = a->nis_window[o] > 1.0 || f->held;
        a->not_referenced[o] = !f->referenced;
        a->x_m[o] = z[X];
        a->v_m_s[o] = z[V];
        a->sd_m[o] = sqrt(fmax(P[X * n + X], 0.0));
        a->load_n[o] = z[LOAD];
        a->temp_offset_c[o] = z[DT];
        a->torque_offset_nm[o] = z[TOFF];
        a->flow_error_m3_s[o] = f->flow_sigma_m3_s * z[EPS];
        a->flow_sigma_m3_s[o] = f->flow_sigma_m3_s;
        f->p_pa[0] = ddh_pressure_pa(rp + b * N_ROWS, z[PA], f->p_pa[0]);
        f->p_pa[1] = ddh_pressure_pa(rp + b * N_ROWS, z[PB], f->p_pa[1]);
        a->pressures_bar[2 * o] = f->p_pa[0] * 1e-5;
        a->pressures_bar[2 * o + 1] = f->p_pa[1] * 1e-5;
    }
    return bad;
}

/* A sample at which no switch changed and no edge was accepted (nearly every one):
 * kf_predict_update and kf_finish in one call. Returns kf_finish's. */
long kf_sample(long B, long n, long k, const struct kf_settings *s,
               const struct kf_unit *units, struct kf_filter *filters, double *z, double *P,
               double *prior_var, struct ddh_params *rp, struct ddh_state *rs,
               struct ddh_input *ri, const struct kf_arrays *a, struct ddh_counters *counters)
{
    kf_predict_update(B, n, k, s, units, filters, z, P, prior_var, rp, rs, ri, a, counters);
    return kf_finish(B, n, k, s, units, filters, z, P, rp, a);
}

/* Samples k0 to k1 - 1, none with an edge: kf_sample each, the loop of an offline run between
 * its edges. Returns k1, or the first sample after which a filter's state is not finite. */
long kf_run(long B, long n, long k0, long k1, const struct kf_settings *s,
            const struct kf_unit *units, struct kf_filter *filters, double *z, double *P,
            double *prior_var, struct ddh_params *rp, struct ddh_state *rs,
            struct ddh_input *ri, const struct kf_arrays *a, struct ddh_counters *counters)
{
    for (long k = k0; k < k1; k++) {
        if (kf_sample(B, n, k, s, units, filters, z, P, prior_var, rp, rs, ri, a, counters))
            return k;
    }
    return k1;
}
