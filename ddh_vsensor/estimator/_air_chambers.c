/* The compressible-chamber model with entrained air (chambers.py), compiled: the diagnosis
 * integrates it over every run for every air fraction it tries, and an extension with air
 * steps it online, so its Python form (numpy over a batch, ~100 us per sample) dominated both.
 *
 * The valves, pumps and torque closure are the dynamic mode's (_chambers.c, included: one
 * arithmetic); this file adds the oil-air mixture law (physics/air.py) and the secant
 * compliance over the step. No end stops and no blend: the model the diagnosis fits.
 * State layout: A_PA, A_PB, A_V, A_X, A_N, A_TAU, A_RA, A_RB, mirrored in chambers.py.
 */
#include "_chambers.c"

#define ATMOSPHERE_PA 101325.0
#define POLYTROPIC_EXPONENT 1.4
#define MIN_ABSOLUTE_PA 1000.0
#define SECANT_MIN_PA 100.0

enum { A_PA, A_PB, A_V, A_X, A_N, A_TAU, A_RA, A_RB, A_SIZE };

int air_sizes(int which) { return which == 0 ? P_SIZE : A_SIZE; }

/* -ln of the mixture's specific volume and its derivative (1/effective bulk modulus). */
static void mixture(double p_gauge, double air, double beta, double reservoir, double *log_d,
                    double *comp)
{
    double p = p_gauge + reservoir + ATMOSPHERE_PA;
    const double below = p < MIN_ABSOLUTE_PA ? p - MIN_ABSOLUTE_PA : 0.0;   /* a cavity */
    if (p < MIN_ABSOLUTE_PA)
        p = MIN_ABSOLUTE_PA;
    double oil = (1.0 - air) * exp(-(p - ATMOSPHERE_PA) / beta);
    double gas = air * pow(ATMOSPHERE_PA / p, 1.0 / POLYTROPIC_EXPONENT);
    double mix = oil + gas;
    *comp = (oil / beta + gas / (POLYTROPIC_EXPONENT * p)) / mix;
    *log_d = -log(mix) + *comp * below;
}

/* Secant compliance over [p0, p1] (the tangent where the step is tiny): exact compression. */
static double secant(double vol, double l0, double inv0, double p0, double p1, double air,
                     double beta, double reservoir, double h)
{
    double dp = p1 - p0, l1, unused;
    if (fabs(dp) <= SECANT_MIN_PA)
        return vol * inv0 / h;
    mixture(p1, air, beta, reservoir, &l1, &unused);
    return vol * ((l1 - l0) / dp) / h;
}

/* One sample h seconds after the last; h <= 0 keeps the state (a repeated stamp). */
void air_step(const double *P, double reservoir, double air, int inertia, double *S, double h,
              double speed_rpm, double torque, double mu)
{
    if (!(h > 0.0))
        return;
    double raw_torque = torque, beta = P[P_BETA], stroke = P[P_STROKE];
    double pa = S[A_PA], pb = S[A_PB], x = S[A_X];
    double q_a = P[P_Q_A] * speed_rpm, q_b = P[P_Q_B] * speed_rpm;
    double g_a = P[P_LEAK_A] / mu, g_b = P[P_LEAK_B] / mu;
    double xv = x < 0.0 ? 0.0 : x > stroke ? stroke : x;
    double vol_a = P[P_DEAD_A] + P[P_AREA_A] * xv;
    double vol_b = P[P_DEAD_B] + P[P_AREA_B] * (stroke - xv);
    if (inertia)    /* the speed's backward difference pairs with the step's mean torque */
        torque = 0.5 * (torque + S[A_TAU]) - P[P_INERTIA] * (speed_rpm - S[A_N]) / h;
    double l_a, inv_a, l_b, inv_b;
    mixture(pa, air, beta, reservoir, &l_a, &inv_a);
    mixture(pb, air, beta, reservoir, &l_b, &inv_b);
    int d = direction(speed_rpm);
    int ra = (int)S[A_RA], rb = (int)S[A_RB];
    double ca = vol_a * inv_a / h, cb = vol_b * inv_b / h, npa, npb, nv;
    solve(P, q_a + ca * pa, q_b + cb * pb, ca + g_a, cb + g_b, torque, d, &ra, &rb, &npa,
          &npb, &nv);
    if (air > 0.0) {
        ca = secant(vol_a, l_a, inv_a, pa, npa, air, beta, reservoir, h);
        cb = secant(vol_b, l_b, inv_b, pb, npb, air, beta, reservoir, h);
        solve(P, q_a + ca * pa, q_b + cb * pb, ca + g_a, cb + g_b, torque, d, &ra, &rb, &npa,
              &npb, &nv);
    }
    S[A_PA] = npa;
    S[A_PB] = npb;
    if (h <= P[P_MAX_GAP_S])    /* trapezoidal, as the estimator integrates its velocities */
        S[A_X] = x + 0.5 * h * (S[A_V] + nv);
    S[A_V] = nv;
    S[A_N] = speed_rpm;
    S[A_TAU] = raw_torque;
    S[A_RA] = ra;
    S[A_RB] = rb;
}

/* A whole run from the state S (its first sample's): positions (m) and pressures per sample. */
void air_track(const double *P, double reservoir, double air, int inertia, double *S, long len,
               const double *t, const double *speed_rpm, const double *torque,
               const double *mu, double *out_x, double *out_pa, double *out_pb)
{
    if (len <= 0)
        return;
    out_x[0] = S[A_X];
    out_pa[0] = S[A_PA];
    out_pb[0] = S[A_PB];
    for (long k = 1; k < len; k++) {
        air_step(P, reservoir, air, inertia, S, t[k] - t[k - 1], speed_rpm[k], torque[k],
                 mu[k]);
        out_x[k] = S[A_X];
        out_pa[k] = S[A_PA];
        out_pb[k] = S[A_PB];
    }
}
