/* Row-wise linear interpolation for the table build: row r of out is scale x numpy.interp(x,
 * xp[r], fp[r]), computed as numpy computes it (the segment j with xp[j] <= x < xp[j+1], the
 * slope (fp[j+1] - fp[j]) / (xp[j+1] - xp[j]), slope (x - xp[j]) + fp[j], a breakpoint's value
 * at x equal to it, the ends' values beyond; the other end of the segment where the
 * slope is infinite), so the tables equal numpy's to the bit. Compiled without contracting
 * multiply-adds. x ascending. */
#include <math.h>

void interp_rows(long rows, long m, long n, const double *xp, const double *fp,
                 const double *x, double scale, double *out)
{
    for (long r = 0; r < rows; r++) {
        const double *xr = xp + r * m, *fr = fp + r * m;
        double *o = out + r * n;
        long j = 0;
        for (long i = 0; i < n; i++) {
            const double xv = x[i];
            double v;
            if (xv < xr[0]) {
                v = fr[0];
            } else if (xv >= xr[m - 1]) {
                v = fr[m - 1];
            } else {
                while (j < m - 2 && xr[j + 1] <= xv)
                    j++;
                if (xr[j] == xv) {
                    o[i] = fr[j] * scale;
                    continue;
                }
                const double slope = (fr[j + 1] - fr[j]) / (xr[j + 1] - xr[j]);
                v = slope * (xv - xr[j]) + fr[j];
                if (isnan(v))
                    v = slope * (xv - xr[j + 1]) + fr[j + 1];
                if (isnan(v) && fr[j] == fr[j + 1])
                    v = fr[j];
            }
            o[i] = v * scale;
        }
    }
}
