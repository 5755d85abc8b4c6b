//! Exact values recorded from Mitsuba 3.9.1 (pip `mitsuba`, variant
//! `scalar_rgb`): `b = mi.load_dict({...}); si = mi.SurfaceInteraction3f();
//! si.wi = d(theta_i, phi_i); si.sh_frame = mi.Frame3f([0,0,1]);
//! b.eval(mi.BSDFContext(), si, d(theta_o, phi_o))` and `b.pdf(...)`, with
//! `d(theta, phi)` the unit vector at those angles in degrees. Mitsuba's
//! `int_ior = 1.5` is relative to air (1.000277), hence `eta = 1.5 / 1.000277`.

#![allow(clippy::excessive_precision)]

use super::{rough_conductor, rough_dielectric};
use crate::*;
use glam::{Vec2, Vec3};

fn d(theta: f64, phi: f64) -> Vec3 {
    let (t, p) = (theta.to_radians(), phi.to_radians());
    Vec3::new(
        (t.sin() * p.cos()) as f32,
        (t.sin() * p.sin()) as f32,
        t.cos() as f32,
    )
}

const AIR: f32 = 1.000277;

/// Direction pairs ((theta_i, phi_i), (theta_o, phi_o)) in degrees.
const PAIRS: [((f64, f64), (f64, f64)); 5] = [
    ((30., 0.), (40., 180.)),
    ((60., 20.), (20., 230.)),
    ((10., 0.), (150., 190.)),
    ((170., 0.), (20., 180.)),
    ((160., 30.), (135., 200.)),
];

fn close(a: f32, b: f32, rel: f32) -> bool {
    (a - b).abs() <= rel * b.abs().max(a.abs()) + 1e-7
}

fn check(name: &str, bsdf: &Bsdf, expected: &[([f32; 3], f32)], rel: f32) {
    for (((ti, pi), (to, po)), (e, p)) in PAIRS.iter().zip(expected) {
        let (wi, wo) = (d(*ti, *pi), d(*to, *po));
        let f = bsdf.eval(wi, wo);
        let pdf = bsdf.pdf(wi, wo);
        let e = Vec3::from(*e);
        for c in 0..3 {
            assert!(
                close(f[c], e[c], rel),
                "{name} {ti},{pi} -> {to},{po}: eval {f} vs mitsuba {e}"
            );
        }
        assert!(
            close(pdf, *p, rel),
            "{name} {ti},{pi} -> {to},{po}: pdf {pdf} vs mitsuba {p}"
        );
    }
}

const Z: ([f32; 3], f32) = ([0.0; 3], 0.0);

/// The rough plastics' coating tables: `rp_ggx`'s, then `rp_beck`'s.
fn rough_plastic_tables() -> [RoughPlasticTable; 2] {
    [
        RoughPlasticTable::new(MicrofacetType::Ggx, 0.2, 1.5 / AIR),
        RoughPlasticTable::new(MicrofacetType::Beckmann, 0.4, 1.33 / AIR),
    ]
}

/// The models the values below were recorded for, by the names the tables use,
/// each with its Mitsuba dict. The rough plastics borrow `tables`
/// ([`rough_plastic_tables`]).
fn model<'t>(name: &str, tables: &'t [RoughPlasticTable; 2]) -> Bsdf<'t> {
    use MicrofacetType::{Beckmann, Ggx};
    let gold = (
        Vec3::new(0.143, 0.374, 1.442),
        Vec3::new(3.983, 2.385, 1.603),
    );
    let (eta, k) = (Vec3::new(0.2, 0.9, 1.1), Vec3::new(3.9, 2.4, 2.2));
    match name {
        // {'type':'roughconductor','distribution':'ggx','alpha':0.3,
        //  'eta':rgb[0.143,0.374,1.442],'k':rgb[3.983,2.385,1.603]}
        "rc_ggx" => rough_conductor(Ggx, (0.3, 0.3), true, gold.0, gold.1),
        // {'type':'roughconductor','distribution':'beckmann','alpha_u':0.1,'alpha_v':0.4,
        //  'eta':rgb[0.2,0.9,1.1],'k':rgb[3.9,2.4,2.2]}
        "rc_beck_aniso" => rough_conductor(Beckmann, (0.1, 0.4), true, eta, k),
        // {'type':'roughconductor','distribution':'ggx','alpha_u':0.3,'alpha_v':0.15,
        //  'sample_visible':False, eta/k as rc_beck_aniso}
        "rc_ggx_nv" => rough_conductor(Ggx, (0.3, 0.15), false, eta, k),
        // {'type':'roughplastic','distribution':'ggx','alpha':0.2,'int_ior':1.5,
        //  'diffuse_reflectance':rgb[0.8,0.3,0.1]}  (specular weight 1/(1+0.4))
        "rp_ggx" => Bsdf::RoughPlastic(RoughPlastic::new(
            &tables[0],
            Vec3::new(0.8, 0.3, 0.1),
            Vec3::ONE,
            false,
            specular_sampling_weight(0.4, 1.0),
            true,
        )),
        // {'type':'roughplastic','distribution':'beckmann','alpha':0.4,'int_ior':1.33,
        //  'diffuse_reflectance':rgb[0.5,0.5,0.5],'nonlinear':True}
        "rp_beck" => Bsdf::RoughPlastic(RoughPlastic::new(
            &tables[1],
            Vec3::splat(0.5),
            Vec3::ONE,
            true,
            specular_sampling_weight(0.5, 1.0),
            true,
        )),
        // {'type':'plastic','int_ior':1.5,'diffuse_reflectance':rgb[0.8,0.3,0.1]}
        "plastic" => Bsdf::Plastic(Plastic::new(
            1.5 / AIR,
            Vec3::new(0.8, 0.3, 0.1),
            Vec3::ONE,
            false,
            specular_sampling_weight(0.4, 1.0),
        )),
        // {'type':'roughdielectric','distribution':'ggx','alpha':0.3,'int_ior':1.5}
        "rd_ggx" => rough_dielectric(Ggx, (0.3, 0.3), true, 1.5 / AIR, Vec3::ONE, Vec3::ONE),
        // {'type':'roughdielectric','distribution':'beckmann','alpha':0.2,'int_ior':1.33}
        "rd_beck" => rough_dielectric(Beckmann, (0.2, 0.2), true, 1.33 / AIR, Vec3::ONE, Vec3::ONE),
        _ => panic!("no recorded model {name}"),
    }
}

/// Mitsuba's eval and pdf at the five [`PAIRS`], per model of [`model`] (the
/// dielectrics' pairs cover both sides), with the relative tolerance.
#[allow(clippy::type_complexity)]
const EVALS: [(&str, [([f32; 3], f32); 5], f32); 7] = [
    (
        "rc_ggx",
        [
            (
                [0.831503689289093, 0.6901191473007202, 0.28225505352020264],
                0.8740200996398926,
            ),
            (
                [0.2614780366420746, 0.2170187532901764, 0.08938624709844589],
                0.27150458097457886,
            ),
            Z,
            Z,
            Z,
        ],
        1e-4,
    ),
    (
        "rc_beck_aniso",
        [
            (
                [1.0320624113082886, 0.6679179668426514, 0.5698191523551941],
                1.084930658340454,
            ),
            (
                [
                    2.0968657565845206e-07,
                    1.3576250523783528e-07,
                    1.1594732285402642e-07,
                ],
                2.2051182213544962e-07,
            ),
            Z,
            Z,
            Z,
        ],
        2e-3,
    ),
    (
        "rp_ggx",
        [
            (
                [0.22181914746761322, 0.1268993765115738, 0.08893146365880966],
                0.39918625354766846,
            ),
            (
                [
                    0.18640929460525513,
                    0.07525576651096344,
                    0.03079434111714363,
                ],
                0.2753608822822571,
            ),
            Z,
            Z,
            Z,
        ],
        1e-3,
    ),
    (
        "rp_beck",
        [
            ([0.09168869256973267; 3], 0.2588920295238495),
            ([0.10473747551441193; 3], 0.3214828670024872),
            Z,
            Z,
            Z,
        ],
        1e-3,
    ),
    (
        "plastic",
        [
            (
                [
                    0.19668716192245483,
                    0.07375768572092056,
                    0.024585895240306854,
                ],
                0.22004066407680511,
            ),
            (
                [
                    0.23059161007404327,
                    0.08647185564041138,
                    0.02882395125925541,
                ],
                0.2403305470943451,
            ),
            Z,
            Z,
            Z,
        ],
        1e-4,
    ),
    (
        "rd_ggx",
        [
            ([0.037008292973041534; 3], 0.03758557513356209),
            ([0.012161227874457836; 3], 0.012197368778288364),
            ([0.05206621438264847; 3], 0.1179557517170906),
            ([14.410000801086426; 3], 6.427037715911865),
            ([0.02667049504816532; 3], 0.027257658541202545),
        ],
        1e-3,
    ),
    (
        "rd_beck",
        [
            ([0.042693473398685455; 3], 0.042693473398685455),
            ([0.0017978816758841276; 3], 0.001797881443053484),
            Z,
            ([8.329730987548828; 3], 4.7115983963012695),
            ([0.017834492027759552; 3], 0.0178344938904047),
        ],
        2e-3,
    ),
];

#[test]
fn eval_and_pdf_match_mitsuba() {
    let tables = rough_plastic_tables();
    for (name, expected, rel) in &EVALS {
        check(name, &model(name, &tables), expected, *rel);
    }
}

#[test]
fn delta_models_match_mitsuba_samples_at_45_degrees() {
    let wi = d(45., 0.);
    // dielectric int_ior 1.5: reflection pdf (= Fresnel) 0.050181858, weight 1.
    let b = Bsdf::Dielectric(Dielectric::new(1.5 / AIR, Vec3::ONE, Vec3::ONE));
    let s = b.sample(wi, 0.01, Vec2::splat(0.5)).unwrap();
    assert!(
        close(s.pdf, 0.050181858241558075, 1e-5)
            && close(s.weight.x, 1.0, 1e-6)
            && !s.lobe.transmission
    );
    // refraction: pdf 0.94981813, wo (-0.471535, 0, -0.881847), weight 0.444691, eta 1.49958
    let s = b.sample(wi, 0.99, Vec2::splat(0.5)).unwrap();
    assert!(
        close(s.pdf, 0.9498181343078613, 1e-5)
            && close(s.weight.x, 0.444691, 1e-5)
            && close(s.eta, 1.4995845556259155, 1e-6)
    );
    assert!((s.wo - Vec3::new(-0.471535, 0.0, -0.881847)).length() < 1e-5 && s.lobe.transmission);
    // leaving the glass at theta = 150 deg: pdf 0.94489914, weight 2.24875, eta 0.66685134
    let s = b.sample(d(150., 0.), 0.99, Vec2::splat(0.5)).unwrap();
    assert!(
        close(s.pdf, 0.9448991417884827, 1e-5)
            && close(s.weight.x, 2.24875, 1e-5)
            && close(s.eta, 0.6668513417243958, 1e-6)
    );
    assert!((s.wo - Vec3::new(-0.749792, 0.0, 0.661673)).length() < 1e-5);
    // thindielectric int_ior 1.5: reflection probability 0.095567942
    let b = Bsdf::ThinDielectric(ThinDielectric::new(1.5 / AIR, Vec3::ONE, Vec3::ONE));
    let s = b.sample(wi, 0.01, Vec2::splat(0.5)).unwrap();
    assert!(close(s.pdf, 0.09556794166564941, 1e-5));
    // conductor (Au-ish): weight (0.965302, 0.801435, 0.33586)
    let b = Bsdf::Conductor(Conductor::new(
        Vec3::new(0.143, 0.374, 1.442),
        Vec3::new(3.983, 2.385, 1.603),
        Vec3::ONE,
    ));
    let s = b.sample(wi, 0.01, Vec2::splat(0.5)).unwrap();
    assert!(
        (s.weight - Vec3::new(0.965302, 0.801435, 0.33586))
            .abs()
            .max_element()
            < 2e-6,
        "{}",
        s.weight
    );
}

/// `bs, w = b.sample(mi.BSDFContext(), si, u1, [u2, u3])` in Mitsuba (same
/// set-up as above): (model, (theta_i, phi_i), (u1, u2, u3), wo, pdf, weight);
/// pdf 0 means Mitsuba produced no sample.
#[allow(clippy::type_complexity)]
const SAMPLES: [(&str, (f64, f64), (f32, f32, f32), [f32; 3], f32, [f32; 3]); 12] = [
    (
        "rc_beck_aniso",
        (30., 10.),
        (0.3, 0.2, 0.7),
        [-0.36158, -0.04396159, 0.9313039],
        1.3634657,
        [0.9517585, 0.61570919, 0.52453744],
    ),
    (
        "rc_beck_aniso",
        (70., 100.),
        (0.8, 0.9, 0.35),
        [0.150637, -0.9787284, 0.1392814],
        4.9941268,
        [0.6768961, 0.49746186, 0.45376912],
    ),
    (
        "rc_beck_aniso",
        (160., 40.),
        (0.6, 0.45, 0.1),
        [0., 0., 0.],
        0.,
        [0., 0., 0.],
    ),
    (
        "rc_ggx_nv",
        (30., 10.),
        (0.3, 0.2, 0.7),
        [-0.5694414, -0.2053726, 0.7959639],
        1.3717998,
        [0.90225846, 0.58384764, 0.49793267],
    ),
    (
        "rc_ggx_nv",
        (70., 100.),
        (0.8, 0.9, 0.35),
        [-0.4100673, -0.5309158, 0.7416017],
        0.046098154,
        [2.0137765, 1.3091973, 1.1248295],
    ),
    (
        "rc_ggx_nv",
        (160., 40.),
        (0.6, 0.45, 0.1),
        [0., 0., 0.],
        0.,
        [0., 0., 0.],
    ),
    (
        "rd_ggx",
        (30., 10.),
        (0.3, 0.2, 0.7),
        [-0.2951144, -0.1218993, -0.9476539],
        11.044722,
        [0.44356057, 0.44356057, 0.44356057],
    ),
    (
        "rd_ggx",
        (70., 100.),
        (0.8, 0.9, 0.35),
        [-0.07823979, -0.7932747, -0.6038161],
        1.0898288,
        [0.42849994, 0.42849994, 0.42849994],
    ),
    (
        "rd_ggx",
        (160., 40.),
        (0.6, 0.45, 0.1),
        [-0.2350114, -0.170366, 0.9569457],
        1.5399364,
        [2.2441175, 2.2441175, 2.2441175],
    ),
    (
        "rp_beck",
        (30., 10.),
        (0.3, 0.2, 0.7),
        [-0.5196153, 0.3, 0.8],
        0.26430753,
        [0.35111097, 0.35111097, 0.35111097],
    ),
    (
        "rp_beck",
        (70., 100.),
        (0.8, 0.9, 0.35),
        [0.7655522, -0.2322277, 0.6000001],
        0.15673293,
        [0.35811725, 0.35811725, 0.35811725],
    ),
    (
        "rp_beck",
        (160., 40.),
        (0.6, 0.45, 0.1),
        [0., 0., 0.],
        0.,
        [0., 0., 0.],
    ),
];

#[test]
fn sampling_routines_reproduce_mitsuba_samples_for_the_same_random_numbers() {
    let tables = rough_plastic_tables();
    for (name, (ti, pi), (u1, u2, u3), wo, pdf, w) in SAMPLES {
        let b = model(name, &tables);
        let s = b.sample(d(ti, pi), u1, Vec2::new(u2, u3));
        if pdf == 0.0 {
            assert!(
                s.is_none(),
                "{name} {ti} {pi}: expected no sample, got {s:?}"
            );
            continue;
        }
        let s = s.unwrap_or_else(|| panic!("{name} {ti} {pi}: no sample"));
        assert!(
            (s.wo - Vec3::from(wo)).length() < 2e-4,
            "{name} {ti} {pi}: wo {} vs {:?}",
            s.wo,
            wo
        );
        assert!(
            close(s.pdf, pdf, 2e-3),
            "{name} {ti} {pi}: pdf {} vs {pdf}",
            s.pdf
        );
        for c in 0..3 {
            assert!(
                close(s.weight[c], w[c], 2e-3),
                "{name} {ti} {pi}: weight {} vs {w:?}",
                s.weight
            );
        }
    }
}
