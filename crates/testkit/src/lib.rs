//! Helpers shared by the test suites (dev-dependency only): their random-number generator,
//! the chi-square distribution (own implementation via the regularised incomplete gamma
//! function), Pearson's test with pooling of small bins, and the Šidák correction.

mod rng;

pub use rng::TestRng;

/// ln Gamma(x) for x > 0 (Lanczos, g = 7, n = 9).
pub fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma Q(a, x) = 1 - P(a, x).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        // Series for P.
        let (mut ap, mut sum) = (a, 1.0 / a);
        let mut del = sum;
        for _ in 0..10_000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * (-x + a * x.ln() - gln).exp()
    } else {
        // Continued fraction for Q (modified Lentz).
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (-x + a * x.ln() - gln).exp() * h
    }
}

/// P(X >= stat) for X ~ chi-square with `dof` degrees of freedom.
pub fn chi2_sf(stat: f64, dof: usize) -> f64 {
    gamma_q(dof as f64 / 2.0, stat / 2.0)
}

/// The chi-square quantile: the x with P(X <= x) = p (bisection on the CDF).
pub fn chi2_quantile(p: f64, dof: usize) -> f64 {
    let (mut lo, mut hi) = (0.0f64, (dof as f64 + 10.0) * 10.0);
    while 1.0 - chi2_sf(hi, dof) < p {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if 1.0 - chi2_sf(mid, dof) < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Per-test significance level after a Šidák correction for `n` tests.
pub fn sidak(alpha: f64, n: usize) -> f64 {
    1.0 - (1.0 - alpha).powf(1.0 / n as f64)
}

/// Pearson chi-square test of `observed` counts against `expected` counts;
/// bins expecting fewer than 5 are pooled into one. Returns the p-value, or 0
/// if a sample fell into a bin of zero expectation.
pub fn pooled_chi2_pvalue(observed: &[f64], expected: &[f64]) -> f64 {
    let (mut stat, mut bins) = (0.0, 0usize);
    let (mut po, mut pe) = (0.0, 0.0);
    for (&o, &e) in observed.iter().zip(expected) {
        if e <= 0.0 {
            if o > 0.0 {
                return 0.0;
            }
            continue;
        }
        if e < 5.0 {
            po += o;
            pe += e;
        } else {
            stat += (o - e) * (o - e) / e;
            bins += 1;
        }
    }
    if pe > 0.0 {
        stat += (po - pe) * (po - pe) / pe;
        bins += 1;
    }
    if bins < 2 {
        return 1.0;
    }
    chi2_sf(stat, bins - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi_square_distribution_matches_tabulated_quantiles() {
        // Tabulated 99% quantiles: dof 1 -> 6.635, dof 10 -> 23.209, dof 100 -> 135.807;
        // 95%: dof 10 -> 18.307.
        for (dof, q) in [(1usize, 6.6349), (10, 23.2093), (100, 135.8067)] {
            assert!(
                (chi2_quantile(0.99, dof) - q).abs() < 2e-3,
                "dof {dof}: {}",
                chi2_quantile(0.99, dof)
            );
            assert!((chi2_sf(q, dof) - 0.01).abs() < 1e-5);
        }
        assert!((chi2_sf(18.307_038, 10) - 0.05).abs() < 1e-6);
        assert!((chi2_sf(2.0, 2) - (-1.0f64).exp()).abs() < 1e-12);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-12);
    }

    #[test]
    fn pooled_test_rejects_a_wrong_distribution_and_accepts_the_right_one() {
        let expected = [100.0, 200.0, 300.0, 400.0, 2.0, 2.0];
        assert!(pooled_chi2_pvalue(&[98.0, 205.0, 296.0, 401.0, 3.0, 1.0], &expected) > 0.5);
        assert!(pooled_chi2_pvalue(&[150.0, 200.0, 250.0, 400.0, 2.0, 2.0], &expected) < 1e-4);
        assert_eq!(pooled_chi2_pvalue(&[1.0], &[0.0]), 0.0);
        assert!((sidak(0.01, 1) - 0.01).abs() < 1e-15 && sidak(0.01, 10) < 0.001006);
    }
}
