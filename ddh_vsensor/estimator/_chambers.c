/* The compressible-chamber step of the estimator's `dynamic` mode (see chambers.py).
 *
 * One sample: backward Euler over the step h for both gauge chamber pressures and the rod
 * velocity, closed by the measured torque; valve regimes from the last step first, all
 * sixteen when that is inconsistent. `run` is the same step over a whole log, so the online
 * and the offline faces share one arithmetic. Layouts of P (parameters) and S (state) are
 * fixed by the P_* / S_* indices below and mirrored in chambers.py.
 */
#include <math.h>

enum {
    P_AREA_A, P_AREA_B, P_STROKE, P_DEAD_A, P_DEAD_B, P_Q_A, P_Q_B, P_LEAK_A, P_LEAK_B,
    P_CRACK, P_RELIEF_A, P_RELIEF_B, P_INERTIA, P_BETA, P_BLEND_S, P_MAX_GAP_S, P_TORQUE_STEP,
    P_WINDOW_S, P_SPEED_LIMIT, P_CURVATURE, P_DISAGREE, P_DISAGREE_FLOOR,
    P_G_A, P_GE_A = P_G_A + 4, P_G_B = P_GE_A + 4, P_GE_B = P_G_B + 4,
    P_K_A = P_GE_B + 4, P_K_B = P_K_A + 12, P_FRIC_C = P_K_B + 12, P_FRIC_V, P_FRIC_S, P_MASS,
    P_START_TOL, P_SIZE
};
/* A rod slower than this (m/s) is at rest: a standing rod's leakage creep, not a move */
#define REST_SPEED 2e-3
#define HF_LEARN 20         /* steps the drive's cadence is first learnt from (see HF_GAIN) */

/* The torque balance's window: the last RING samples' mean motor torques, the speeds
 * before them and their lengths (a ring from S_RING, S_RING_AT the next slot, S_RING_COUNT
 * those filled). */
#define RING 32
enum { S_PA, S_PB, S_V, S_X, S_N, S_TAU, S_RA, S_RB, S_SA, S_SB, S_STARTED, S_HF, S_PUMP_TAU,
       S_LOAD_F, S_HF_COUNT, S_HF_DEV, S_RING_AT, S_RING_COUNT, S_RING,
       S_LEARN = S_RING + 3 * RING, S_TAU2 = S_LEARN + HF_LEARN, S_LEFT, S_SIZE };

/* The drive samples on an even cadence; the frames' receive stamps come late by a varying
 * delay. The step is taken over the drive's periods, not the stamps' difference: a short
 * difference is a late frame followed by a prompt one, and one rpm over it read as inertia
 * torque (100 N m at 1 kHz); a long one is a frame lost or a late one. They are told apart
 * at LOST_AT periods, where delays varying by less than half a period leave no doubt; where
 * they vary more (the steps' mean deviation S_HF_DEV, a third of the delays' range) a lost
 * frame is only counted beyond the longest late step, 1 + JITTER_SPAN x the deviation. The
 * cadence is the median step of the first HF_LEARN steps (S_LEARN), then filtered (HF_GAIN)
 * per period: lost frames do not lengthen it. */
#define HF_GAIN 0.05
#define LOST_AT 1.5
#define JITTER_SPAN 3.6

int chambers_sizes(int which) { return which == 0 ? P_SIZE : S_SIZE; }

static int regime(double dp, double crack, double relief)
{
    return (dp >= crack) + (dp >= 0.0) + (dp > relief);
}

/* In regimes ra, rb each chamber's pressure is linear in the rod's speed: p = al + be * v. */
static void linear(const double *P, int ra, int rb, double fa, double fb, double da, double db,
                   double *al_a, double *be_a, double *al_b, double *be_b)
{
    double den_a = da + P[P_G_A + ra], den_b = db + P[P_G_B + rb];
    *al_a = (fa + P[P_GE_A + ra]) / den_a; *be_a = -P[P_AREA_A] / den_a;
    *al_b = (fb + P[P_GE_B + rb]) / den_b; *be_b = P[P_AREA_B] / den_b;
}

/* The rod's speed at the step's end from its equation of motion with the empty machine's
 * mass, m (v - v0) / h = F(v) - resist - c_v v, F(v) the chambers' force at speed v (the
 * pressures of linear()) and resist the load and friction it works against. */
static double rod_speed(const double *P, double al_a, double be_a, double al_b, double be_b,
                        double v0, double h, double resist)
{
    double m = P[P_MASS];
    return (P[P_AREA_A] * al_a - P[P_AREA_B] * al_b - resist + m * v0 / h)
           / (m / h - P[P_AREA_A] * be_a + P[P_AREA_B] * be_b + P[P_FRIC_V]);
}

static void attempt(const double *P, int ra, int rb, double fa, double fb, double da,
                    double db, double torque, int d, double *pa, double *pb, double *v)
{
    double al_a, be_a, al_b, be_b;
    linear(P, ra, rb, fa, fb, da, db, &al_a, &be_a, &al_b, &be_b);
    double k_a = P[P_K_A + 4 * d + ra], k_b = P[P_K_B + 4 * d + rb];
    *v = (torque - k_a * al_a - k_b * al_b) / (k_a * be_a + k_b * be_b);
    *pa = al_a + be_a * *v;
    *pb = al_b + be_b * *v;
}

static double outside(double p, int r, double crack, double relief)
{
    double lo = r == 0 ? -INFINITY : r == 1 ? crack : r == 2 ? 0.0 : relief;
    double hi = r == 0 ? crack : r == 1 ? 0.0 : r == 2 ? relief : INFINITY;
    return (p < lo ? lo - p : 0.0) + (p > hi ? p - hi : 0.0);
}

/* Pressures and velocity for inflows f at zero pressure and conductances d; regimes *ra, *rb
 * are the first guess and come back as the consistent ones. */
static void solve(const double *P, double fa, double fb, double da, double db, double torque,
                  int d, int *ra, int *rb, double *pa, double *pb, double *v)
{
    double crack = P[P_CRACK], rel_a = P[P_RELIEF_A], rel_b = P[P_RELIEF_B];
    attempt(P, *ra, *rb, fa, fb, da, db, torque, d, pa, pb, v);
    if (regime(*pa, crack, rel_a) == *ra && regime(*pb, crack, rel_b) == *rb)
        return;
    double best = INFINITY;
    int best_a = 0, best_b = 0;
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            double qa, qb, qv;
            attempt(P, i, j, fa, fb, da, db, torque, d, &qa, &qb, &qv);
            double out = outside(qa, i, crack, rel_a) + outside(qb, j, crack, rel_b);
            if (out < best) {
                best = out; best_a = i; best_b = j; *pa = qa; *pb = qb; *v = qv;
            }
        }
    *ra = best_a;
    *rb = best_b;
}

/* One chamber's pressure with the rod still, from its own flows, in its consistent regime. */
static void still(const double *P, int g, int ge, double relief, double f, double d, int *r,
                  double *p)
{
    for (int i = 0; i < 4; i++) {
        *r = i;
        *p = (f + P[ge + i]) / (d + P[g + i]);
        if (regime(*p, P[P_CRACK], relief) == i)
            return;
    }
}

/* Both pressures at a rod speed the step has chosen: each chamber's own flows, its valves
 * included (a rod held back from the torque's speed leaves the pumps' flow to them). */
static void at_speed(const double *P, double fa, double fb, double da, double db, double v,
                     int *ra, int *rb, double *pa, double *pb)
{
    still(P, P_G_A, P_GE_A, P[P_RELIEF_A], fa - P[P_AREA_A] * v, da, ra, pa);
    still(P, P_G_B, P_GE_B, P[P_RELIEF_B], fb + P[P_AREA_B] * v, db, rb, pb);
}

static int direction(double n) { return n > 0.0 ? 2 : n < 0.0 ? 0 : 1; }

/* This step's length in the drive's periods (see HF_GAIN). */
static double drive_step(double *S, double h)
{
    double hf = S[S_HF], dev = S[S_HF_DEV];
    int count = (int)S[S_HF_COUNT];
    if (count < HF_LEARN) {
        double *learnt = S + S_LEARN;       /* sorted */
        int i = count;
        for (; i > 0 && learnt[i - 1] > h; i--)
            learnt[i] = learnt[i - 1];
        learnt[i] = h;
        S[S_HF] = 0.5 * (learnt[count / 2] + learnt[(count + 1) / 2]);
        S[S_HF_COUNT] = count + 1;
        return count > 0 ? S[S_HF] : h;
    }
    double lost_at = fmax(LOST_AT, 1.0 + JITTER_SPAN * dev);
    double periods = h < lost_at * hf ? 1.0 : floor(h / hf + 0.5);
    if (periods == 1.0)
        S[S_HF_DEV] = dev + HF_GAIN * (fabs(h - hf) / hf - dev);
    S[S_HF] = hf + HF_GAIN * (h / periods - hf);
    return periods * hf;
}

/* Below the limit, within its last rpm (the limit may be reached just after such a reading),
 * or at it: the speed's zones, whose changes are the limit's edges. */
static int limit_zone(const double *P, double n)
{
    return (fabs(n) >= P[P_SPEED_LIMIT]) + (fabs(n) >= P[P_SPEED_LIMIT] + 1.0);
}

/* The steady state at this speed and (pump) torque: the step with no compliance. */
static void settle(const double *P, double *S, double n, double torque, double mu)
{
    int ra = (int)S[S_SA], rb = (int)S[S_SB];
    double pa, pb, v;
    solve(P, P[P_Q_A] * n, P[P_Q_B] * n, P[P_LEAK_A] / mu, P[P_LEAK_B] / mu, torque,
          direction(n), &ra, &rb, &pa, &pb, &v);
    S[S_PA] = pa; S[S_PB] = pb; S[S_V] = v;
    S[S_RA] = S[S_SA] = ra; S[S_RB] = S[S_SB] = rb;
}

/* One sample h seconds after the last; returns the rod velocity (m/s). A first sample, and
 * one after a gap longer than max_gap_s, starts settled and does not move the rod. */
double chambers_step(const double *P, double *S, double h, double n, double tau, double mu)
{
    if (S[S_STARTED] == 0.0 || !(h > 0.0) || h > P[P_MAX_GAP_S]) {
        if (S[S_STARTED] == 0.0 || h > 0.0) {
            settle(P, S, n, tau, mu);
            S[S_N] = n; S[S_TAU] = S[S_TAU2] = tau; S[S_STARTED] = 1.0; S[S_HF] = 0.0;
            S[S_HF_COUNT] = 0.0; S[S_HF_DEV] = 0.0;
            S[S_PUMP_TAU] = tau; S[S_RING_AT] = 0.0; S[S_RING_COUNT] = 0.0; S[S_LEFT] = 0.0;
        }
        return S[S_V];
    }
    double pa = S[S_PA], pb = S[S_PB], x = S[S_X], stroke = P[P_STROKE];
    /* x is NaN while the rod's position is unknown (never referenced): chamber volumes at
     * mid-stroke, and no end stop, which would otherwise be met at a made-up position */
    int known = x == x;
    double xv = !known ? 0.5 * stroke : x < 0.0 ? 0.0 : x > stroke ? stroke : x;
    /* The speed's backward difference is the rotor's mean acceleration over the step: it
     * pairs with the step's mean motor torque. The speed comes in whole rpm, so over a
     * millisecond its difference reads J x 1 rpm / 1 ms of inertia torque (3 N m on the
     * loader's bucket) that is quantisation, and the valves keep what that noise pushes
     * into a pressure: the balance is taken over the last samples spanning the window
     * (P_WINDOW_S, the drive cadence the rules were measured at), one sample when they are
     * that slow already. */
    double hn = drive_step(S, h);
    /* the window: this step and the ones before it while each brings its span nearer */
    int at = (int)S[S_RING_AT], count = (int)S[S_RING_COUNT];
    double span = hn, earlier = 0.0, n_first = S[S_N];
    for (int i = 1; i <= count && i < RING; i++) {
        int slot = (at - i + RING) % RING;
        double d = S[S_RING + 2 * RING + slot];
        if (!(span + 0.5 * d < P[P_WINDOW_S]))
            break;
        span += d;
        earlier += S[S_RING + slot] * d;
        n_first = S[S_RING + RING + slot];
    }
    earlier /= span;
    double w = hn / span;                   /* 1 for a window of one sample */
    double inertia = P[P_INERTIA] * (n - n_first) / span;
    double mean = 0.5 * (tau + S[S_TAU]);
    double torque = earlier + w * mean - inertia;
    /* A torque step within the sample (the drive reaching its speed limit, the PID reversing
     * off an end stop) has an unknown shape: the step's mean lies somewhere between the two
     * ends, and the endpoints' mean read as pump torque is a wrong pressure that a one-way
     * valve or the torque-blind common mode of the two chambers keeps. The pump torque
     * (the pressures) changes smoothly, so the mean is the value in that range nearest the
     * last step's. Whatever the step's size where the speed reaches or leaves the drive's
     * speed limit within the sample: the limiter takes over from the torque command there
     * (or hands back to it), and the acceleration ends or starts at an unknown instant. The
     * speed comes in whole rpm, so a reading one below the limit may be the limit reached
     * just after the sample or not yet: the band [limit - 1, limit) is a zone of its own,
     * and entering or leaving any zone is the edge (the drop may come in either sample).
     * The step after the edge is one too: the limiter took over (or handed back) at an
     * unknown instant of the last step, and the torque settles to its new course within
     * this one, so the trapezoid of its samples is no better a mean. */
    int limit_edge = limit_zone(P, n) != limit_zone(P, S[S_N]);
    /* the last step, from the ring: its length (a frame may have been lost) and the speed
     * before it (the speed now where there is none) */
    int last = (at - 1 + RING) % RING;
    double n_before = count > 0 ? S[S_RING + RING + last] : S[S_N];
    limit_edge |= limit_zone(P, S[S_N]) != limit_zone(P, n_before);
    /* Below that, the samples are instants of a torque that may still bend between them
     * (the drive's loop swinging faster than it is sampled): the trapezoid is the step's
     * mean where the torque changes linearly, and off by a share of the bend where it does
     * not. The bend is the second difference of the last three samples; within P_CURVATURE
     * of it the mean is again the value nearest the last (a bend is a peak between the
     * samples as often as not: a braking motor's torque 7, 59, 62 N m peaked past 62).
     * The speed has a say too: it integrates the motor torque, so its second difference is
     * the change of the steps' mean motor torque from the last step to this one, wherever the
     * pump torque stays (as it mostly does); the trapezoids say (tau - tau'')/2. Where they
     * disagree by more than a floor (the pump torque's own change within a step, the speed's
     * whole rpm), P_DISAGREE of the excess is how far this step's mean may lie off: up to a
     * whole change past the trapezoid, as a swing between the samples may peak beyond both,
     * this step's change or the last one's, whichever is larger (samples either side of a
     * peak change little however large the swing: a torque ringing at a quarter of the
     * sampling rate); the bend's band too. */
    double jump = fabs(tau - S[S_TAU]);
    double excess = 0.0;
    if (count > 0) {
        double said = P[P_INERTIA] * ((n - S[S_N]) / hn - (S[S_N] - n_before)
                                                          / S[S_RING + 2 * RING + last]);
        excess = fabs(said - 0.5 * (tau - S[S_TAU2])) - P[P_DISAGREE_FLOOR];
    }
    double swing = fmax(jump, fabs(S[S_TAU] - S[S_TAU2]));
    double band = fmin(fmax(P[P_CURVATURE] * fabs(tau - 2.0 * S[S_TAU] + S[S_TAU2]),
                            P[P_DISAGREE] * excess), swing);
    if (jump > P[P_TORQUE_STEP] || limit_edge)
        band = fmax(band, 0.5 * jump);
    if (band > 0.0) {
        double lo = torque - w * band, hi = torque + w * band;
        double last = S[S_PUMP_TAU];
        torque = last < lo ? lo : last > hi ? hi : last;
        mean = (torque + inertia - earlier) / w;
    }
    S[S_RING + at] = mean;
    S[S_RING + RING + at] = S[S_N];
    S[S_RING + 2 * RING + at] = hn;
    S[S_RING_AT] = (at + 1) % RING;
    S[S_RING_COUNT] = count < RING ? count + 1 : RING;
    S[S_PUMP_TAU] = torque;
    double ga = P[P_LEAK_A] / mu, gb = P[P_LEAK_B] / mu;
    double ca = (P[P_DEAD_A] + P[P_AREA_A] * xv) / (P[P_BETA] * hn);
    double cb = (P[P_DEAD_B] + P[P_AREA_B] * (stroke - xv)) / (P[P_BETA] * hn);
    double fa = P[P_Q_A] * n + ca * pa, fb = P[P_Q_B] * n + cb * pb;
    double da = ca + ga, db = cb + gb;
    /* pumping or motoring: over the step, as the mean torque (a reversal within the step
     * would otherwise switch the efficiencies a whole step early) */
    int d = direction(n + S[S_N]);
    /* Where the pumps stand at either end of the step or reverse within it, their friction
     * is static for a moment and the step's mean torque mixes the motoring and the pumping
     * one: any torque between the two holds the pressures. Within that band the torque says
     * nothing about them (outside it, the pumps slip the way it points). Read as pressure, a
     * drive easing its torque off a standing pump under load let the model's chamber fall
     * (B 1.2 bar low on the mean of the bucket's holds, A up to 13 bar on a loaded boom's)
     * and its rod sink by leakage it does not have, or move it off an end stop and back,
     * where the stop keeps the travel as a one-way valve keeps volume. */
    int ra = (int)S[S_RA], rb = (int)S[S_RB];
    if (n * S[S_N] <= 0.0) {
        double t_neg = P[P_K_A + ra] * pa + P[P_K_B + rb] * pb;
        double t_pos = P[P_K_A + 8 + ra] * pa + P[P_K_B + 8 + rb] * pb;
        if (torque >= fmin(t_neg, t_pos) && torque <= fmax(t_neg, t_pos))
            torque = P[P_K_A + 4 * d + ra] * pa + P[P_K_B + 4 * d + rb] * pb;
        else
            d = (torque > fmax(t_neg, t_pos)) == (t_pos > t_neg) ? 2 : 0;
    }
    if (P[P_BLEND_S] > 0.0) {
        /* pulled towards the steady state with time constant blend_s (model errors) */
        int sa = (int)S[S_SA], sb = (int)S[S_SB];
        double qa, qb, qv;
        solve(P, P[P_Q_A] * n, P[P_Q_B] * n, ga, gb, torque, d, &sa, &sb, &qa, &qb, &qv);
        S[S_SA] = sa; S[S_SB] = sb;
        double ka = ca * hn / P[P_BLEND_S], kb = cb * hn / P[P_BLEND_S];
        fa += ka * qa; fb += kb * qb; da += ka; db += kb;
    }
    double load = S[S_LOAD_F];
    double beyond = -1.0;       /* force beyond what holds the rod on its stop (N); < 0: none */
    double v = 0.0;
    int still_done = 0;         /* pa, pb, ra, rb already the chambers' own (rod still) */
    /* A rod on its end stop stays there unless the motor drives it away: pressed into the
     * stop, the pumps' flow goes over the relief valve (a fraction of a bar of pressure error
     * would read as travel); with the motor stopped, leakage decompresses the chambers. */
    int stopped = known && ((x <= 0.0 && n <= 0.0) || (x >= stroke && n >= 0.0));
    if (!stopped && known && (x <= 0.0 || x >= stroke) && load == load) {
        /* Driven away from its stop, the rod stays until the chambers' force overcomes the
         * load it held arriving (the load does not change on the stop) and the rod's static
         * friction: until then the pumps' flow (de)compresses the chambers, which the
         * torque, read as pressure, would turn into travel. Both chambers pinned by their
         * valves the way that pushes the rod off the stop (off the bottom: A on its relief,
         * B on its anti-cavitation valve; off the top the other way) are the most force they
         * can make that way: the load cannot be more. Pinned otherwise (both on their
         * reliefs as the pumps reverse, the stiff chamber at the stop filling within a
         * sample) they still press the rod onto the stop. */
        int qa, qb;
        double sa, sb;
        at_speed(P, fa, fb, da, db, 0.0, &qa, &qb, &sa, &sb);
        double force = sa * P[P_AREA_A] - sb * P[P_AREA_B];
        int pinned = x <= 0.0 ? qa == 3 && qb == 0 : qa == 0 && qb == 3;
        beyond = x <= 0.0 ? force - load - P[P_FRIC_S] : load - P[P_FRIC_S] - force;
        stopped = still_done = !pinned && beyond < 0.0;
        if (still_done) {
            pa = sa; ra = qa; pb = sb; rb = qb;
        }
    }
    if (!stopped) {
        solve(P, fa, fb, da, db, torque, d, &ra, &rb, &pa, &pb, &v);
        /* Both chambers on a one-way valve (relief, anti-cavitation): their pressures are
         * pinned, and the torque, which only sees pressures, cannot tell the rod's speed (a
         * newton-metre of error reads as hundreds of mm/s). The valves take the flow. */
        stopped = (ra == 0 || ra == 3) && (rb == 0 || rb == 3);
        /* Leaving the stop, the rod and its load (their mass, at least the empty machine's)
         * take up speed from the force beyond what held them, which grows from nothing
         * within the step: half its end value on average. Read from the torque alone, the
         * rod went at once; the pumps' flow it cannot take yet compresses the chambers, as far
         * as their valves let it (the pumps turn at speed already: taken in the torque's
         * valve regimes, the boom's rod side read 230 bar at a 76 bar relief). */
        double vmax = 0.5 * beyond / P[P_MASS] * h;
        if (!stopped && beyond > 0.0 && S[S_V] == 0.0 && fabs(v) > vmax) {
            v = copysign(vmax, v);
            at_speed(P, fa, fb, da, db, v, &ra, &rb, &pa, &pb);
        }
        if (!stopped && S[S_LEFT] * v > 0.0 && load == load) {
            /* The sample after the rod left its end stop: it goes on taking up speed with its
             * mass from the force beyond the load it held there (m (v - v0) / h = F(v) - load
             * - friction), which the torque, read as pressure, would again give it at once;
             * the flow it does not take, the chambers and their valves do. */
            double al_a, be_a, al_b, be_b, sg = S[S_LEFT];
            linear(P, ra, rb, fa, fb, da, db, &al_a, &be_a, &al_b, &be_b);
            double vd = rod_speed(P, al_a, be_a, al_b, be_b, S[S_V], hn,
                                  load + sg * P[P_FRIC_C]);
            if (sg * vd > 0.0 && sg * v > sg * vd) {
                v = vd;
                at_speed(P, fa, fb, da, db, v, &ra, &rb, &pa, &pb);
            }
        }
        if (!stopped && beyond <= 0.0 && fabs(S[S_V]) <= REST_SPEED) {
            /* A rod at rest mid-stroke starts with the force that starts it: it held its load
             * within its static friction at the chambers' last force, so it takes up speed
             * only the way that force has changed beyond the friction, and no faster than the
             * change gives the empty machine's mass (m (v - v0) / h = F(v) - F0 -+ F_s - c_v
             * (v - v0), F(v) the chambers' force at speed v, h in the drive's periods). A
             * torque that says more, by more than P_START_TOL of acceleration, is misread (a
             * PID kick or ring between the samples), and the pumps' flow the rod cannot take
             * compresses the chambers. */
            double al_a, be_a, al_b, be_b, v0 = S[S_V];
            linear(P, ra, rb, fa, fb, da, db, &al_a, &be_a, &al_b, &be_b);
            double held = S[S_PA] * P[P_AREA_A] - S[S_PB] * P[P_AREA_B] - P[P_FRIC_V] * v0;
            double lo = fmin(v0, rod_speed(P, al_a, be_a, al_b, be_b, v0, hn,
                                           held + P[P_FRIC_S])) - P[P_START_TOL] * hn;
            double hi = fmax(v0, rod_speed(P, al_a, be_a, al_b, be_b, v0, hn,
                                           held - P[P_FRIC_S])) + P[P_START_TOL] * hn;
            if (v < lo || v > hi) {
                v = v < lo ? lo : hi;
                pa = al_a + be_a * v;
                pb = al_b + be_b * v;
            }
        }
    }
    if (stopped && !still_done)
        at_speed(P, fa, fb, da, db, 0.0, &ra, &rb, &pa, &pb);
    if (stopped)
        v = 0.0;
    double x_new = x + 0.5 * h * (S[S_V] + v);
    S[S_X] = x_new < 0.0 ? 0.0 : x_new > stroke ? stroke : x_new;
    /* the rod left its end stop in this sample (the way it went), for the next */
    S[S_LEFT] = beyond > 0.0 && S[S_V] == 0.0 && v != 0.0 ? (v > 0.0 ? 1.0 : -1.0) : 0.0;
    S[S_PA] = pa; S[S_PB] = pb; S[S_V] = v; S[S_N] = n;
    S[S_TAU2] = S[S_TAU]; S[S_TAU] = tau;
    S[S_RA] = ra; S[S_RB] = rb;
    if (v != 0.0 && known)      /* the load: the chambers' force less the moving friction */
        S[S_LOAD_F] = pa * P[P_AREA_A] - pb * P[P_AREA_B]
                      - copysign(P[P_FRIC_C] + P[P_FRIC_V] * fabs(v), v);
    return v;
}

/* The step over a whole log: t, n, tau, mu in; v (m/s) out. */
void chambers_run(const double *P, double *S, long count, const double *t, const double *n,
                  const double *tau, const double *mu, double *v, double t_last)
{
    for (long k = 0; k < count; k++) {
        double h = S[S_STARTED] == 0.0 ? 0.0 : t[k] - t_last;
        v[k] = chambers_step(P, S, h, n[k], tau[k], mu[k]);
        t_last = t[k];
    }
}
