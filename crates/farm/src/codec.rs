//! Binary forms of what travels between the coordinator and workers besides the guide's own
//! wire forms (trees: [`pathfarm_guide::SdTree::encode`], statistics:
//! [`pathfarm_guide::IterationStats::encode`]): the learned fractions of a pass, the pixel
//! estimate, a tile's pixels (sums, or samples for a unit of few samples per pixel), and the
//! pass spec in its proto form. All little-endian,
//! each with a 4-byte magic and a version byte, decoded with length checks (a payload comes
//! from the network).

use pathfarm_guide::fraction::FractionState;
use pathfarm_proto::v1;
use pathfarm_render::film::PixelStats;
use pathfarm_render::pass::{PassKind, PassSpec, TileOutput, TilePixels};
use pathfarm_render::{Film, Region};

/// A payload that does not decode.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CodecError {
    #[error("{what}: bad magic or version")]
    Header { what: &'static str },
    #[error("{what}: {got} bytes, expected {expected}")]
    Length {
        what: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("pass spec: unknown pass kind {0}")]
    Kind(i32),
    #[error("tile region {0:?} is empty or not inside the image")]
    Region(Region),
    #[error("tile samples: sample {0} is not finite")]
    NonFinite(usize),
    #[error("tile samples: sample {index} has value {value:e}, beyond {MAX_SAMPLE_VALUE:e}")]
    OutOfRange { index: usize, value: f32 },
    #[error("tile estimate: pixel {index} has value {value:e}, not a finite value >= 0")]
    BadEstimate { index: usize, value: f32 },
    #[error("tile pixels: pixel {index}: {why}")]
    BadSums { index: usize, why: &'static str },
}

/// The largest sample value a tile may carry: orders of magnitude past any physically based
/// scene's radiance (the sun is about 1e9 W/(m² sr)), far below where sums would lose their
/// meaning. A larger value is a bug or a hostile peer, and the tile is refused.
pub const MAX_SAMPLE_VALUE: f32 = 1e20;

const VERSION: u8 = 1;

fn header(magic: &[u8; 4]) -> Vec<u8> {
    let mut v = magic.to_vec();
    v.push(VERSION);
    v
}

/// The body after the header, whose length must be `count * item`.
fn body<'a>(
    bytes: &'a [u8],
    magic: &[u8; 4],
    what: &'static str,
    item: usize,
) -> Result<(&'a [u8], usize), CodecError> {
    if bytes.len() < 9 || &bytes[..4] != magic || bytes[4] != VERSION {
        return Err(CodecError::Header { what });
    }
    let count = u32::from_le_bytes(bytes[5..9].try_into().unwrap()) as usize;
    let rest = &bytes[9..];
    let expected = count.saturating_mul(item);
    if rest.len() != expected {
        return Err(CodecError::Length {
            what,
            got: rest.len(),
            expected,
        });
    }
    Ok((rest, count))
}

fn f64_at(b: &[u8], i: usize) -> f64 {
    f64::from_le_bytes(b[8 * i..8 * i + 8].try_into().unwrap())
}

/// The learned-fraction states of every leaf ([`pathfarm_guide::SdTree::fraction_states`]).
pub fn encode_fractions(states: &[FractionState]) -> Vec<u8> {
    let mut v = header(b"PFFR");
    v.extend_from_slice(&(states.len() as u32).to_le_bytes());
    for s in states {
        for x in [s.theta, s.m, s.v] {
            v.extend_from_slice(&x.to_le_bytes());
        }
        v.extend_from_slice(&s.t.to_le_bytes());
    }
    v
}

pub fn decode_fractions(bytes: &[u8]) -> Result<Vec<FractionState>, CodecError> {
    let (b, n) = body(bytes, b"PFFR", "fractions", 32)?;
    Ok((0..n)
        .map(|i| {
            let c = &b[32 * i..32 * i + 32];
            FractionState {
                theta: f64_at(c, 0),
                m: f64_at(c, 1),
                v: f64_at(c, 2),
                t: u64::from_le_bytes(c[24..32].try_into().unwrap()),
            }
        })
        .collect())
}

/// The per-pixel value estimate ([`pathfarm_render::session::Session::estimate`]).
pub fn encode_estimate(estimate: &[f32]) -> Vec<u8> {
    let mut v = header(b"PFES");
    v.extend_from_slice(&(estimate.len() as u32).to_le_bytes());
    for x in estimate {
        v.extend_from_slice(&x.to_le_bytes());
    }
    v
}

/// The most bytes of estimate a lease carries inline (`Lease.tile_estimate`); a larger
/// tile's lease names the whole estimate's blob instead.
pub const MAX_TILE_ESTIMATE_BYTES: usize = 1 << 20;

/// The frame's pixel `estimate` (`width` pixels a row) over `region`, as a lease carries
/// it (`Lease.estimate`), or `None` if its values are more than [`MAX_TILE_ESTIMATE_BYTES`]
/// (or there is no estimate).
pub fn encode_tile_estimate(
    estimate: &[f32],
    width: u32,
    region: Region,
) -> Option<v1::PixelEstimate> {
    let bytes = region.pixels() * 4;
    if estimate.is_empty() || bytes > MAX_TILE_ESTIMATE_BYTES {
        return None;
    }
    let mut v = vec![0u8; bytes];
    let row_bytes = (region.width() as usize * 4).max(1);
    // Row by row into fixed-size chunks: a loop the compiler turns into block copies (one
    // `extend_from_slice` a value was a capacity check a value, under the state lock).
    for (y, out) in (region.y0..region.y1).zip(v.chunks_exact_mut(row_bytes)) {
        let row = (y * width) as usize;
        let line = &estimate[row + region.x0 as usize..row + region.x1 as usize];
        for (o, x) in out.chunks_exact_mut(4).zip(line) {
            o.copy_from_slice(&x.to_le_bytes());
        }
    }
    Some(v1::PixelEstimate {
        region: Some(region_to_proto(region)),
        values: v,
    })
}

/// A frame-sized (`width x height`) estimate holding a lease's part `e` (as
/// [`encode_tile_estimate`] wrote it) over its region and zero elsewhere. Refused unless
/// its region lies in the frame and contains `tile` (the lease reads the estimate there),
/// and it holds exactly the region's pixels, each finite and not negative.
pub fn decode_tile_estimate(
    e: &v1::PixelEstimate,
    (width, height): (u32, u32),
    tile: Region,
) -> Result<Vec<f32>, CodecError> {
    let region = region_from_proto(&e.region.unwrap_or_default(), width, height)?;
    let contains = region.x0 <= tile.x0
        && region.y0 <= tile.y0
        && tile.x1 <= region.x1
        && tile.y1 <= region.y1;
    if !contains {
        return Err(CodecError::Region(region));
    }
    let bytes = &e.values;
    let expected = region.pixels() * 4;
    if bytes.len() != expected {
        let what = "lease estimate";
        let got = bytes.len();
        return Err(CodecError::Length {
            what,
            got,
            expected,
        });
    }
    let mut out = vec![0.0f32; width as usize * height as usize];
    let values = (bytes.chunks_exact(4)).map(|b| f32::from_le_bytes(b.try_into().unwrap()));
    let (w, rw) = (width as usize, region.width() as usize);
    for (i, v) in values.enumerate() {
        if !(v.is_finite() && v >= 0.0) {
            return Err(CodecError::BadEstimate { index: i, value: v });
        }
        let (x, y) = (region.x0 as usize + i % rw, region.y0 as usize + i / rw);
        out[y * w + x] = v;
    }
    Ok(out)
}

pub fn decode_estimate(bytes: &[u8]) -> Result<Vec<f32>, CodecError> {
    let (b, n) = body(bytes, b"PFES", "estimate", 4)?;
    Ok((0..n)
        .map(|i| f32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap()))
        .collect())
}

/// A tile's pixel sums, exactly (raw bits, [`PixelStats::write_le`]).
pub fn encode_pixels(film: &Film) -> Vec<u8> {
    let mut v = header(b"PFPX");
    v.reserve(4 + film.pixels.len() * PixelStats::BYTES);
    v.extend_from_slice(&(film.pixels.len() as u32).to_le_bytes());
    film.pixels.iter().for_each(|p| p.write_le(&mut v));
    v
}

/// The film of `region` from [`encode_pixels`]; the pixel count must match the region.
pub fn decode_pixels(bytes: &[u8], region: Region) -> Result<Film, CodecError> {
    let (b, n) = body(bytes, b"PFPX", "tile pixels", PixelStats::BYTES)?;
    if n != region.pixels() {
        return Err(CodecError::Length {
            what: "tile pixels (pixel count)",
            got: n,
            expected: region.pixels(),
        });
    }
    let mut film = Film::new(region.width(), region.height());
    for (p, c) in film
        .pixels
        .iter_mut()
        .zip(b.chunks_exact(PixelStats::BYTES))
    {
        *p = PixelStats::read_le(c.try_into().unwrap());
    }
    Ok(film)
}

/// A tile's pixels: its sums ([`encode_pixels`]) or its samples (`PFSM`: the count, then
/// three f32 a sample, raw bits).
pub fn encode_tile_pixels(pixels: &TilePixels) -> Vec<u8> {
    match pixels {
        TilePixels::Sums(film) => encode_pixels(film),
        TilePixels::Prepared(r) => encode_tile_pixels(&TilePixels::Samples(r.values())),
        TilePixels::Samples(values) => {
            let mut v = header(b"PFSM");
            v.reserve(4 + values.len() * 12);
            v.extend_from_slice(&(values.len() as u32).to_le_bytes());
            for x in values.iter().flat_map(|s| s.to_array()) {
                v.extend_from_slice(&x.to_le_bytes());
            }
            v
        }
    }
}

/// The bytes [`encode_tile_pixels`] gives a tile of `region` of `spec`: what an upload of
/// it must announce.
pub fn tile_pixels_bytes(spec: &PassSpec, region: Region) -> u64 {
    let pixels = region.pixels() as u64;
    let body = match spec.sample_form() {
        true => pixels * spec.unit_spp() * 12,
        false => pixels * PixelStats::BYTES as u64,
    };
    9 + body
}

/// The pixels of a tile of `region` of `spec` from [`encode_tile_pixels`], in the form the
/// unit's tiles have ([`PassSpec::sample_form`]); samples must be finite (a renderer
/// writes zero for a non-finite estimate).
pub fn decode_tile_pixels(
    bytes: &[u8],
    spec: &PassSpec,
    region: Region,
) -> Result<TilePixels, CodecError> {
    if !spec.sample_form() {
        let film = decode_pixels(bytes, region)?;
        for (index, p) in film.pixels.iter().enumerate() {
            check_sums(p).map_err(|why| CodecError::BadSums { index, why })?;
        }
        return Ok(TilePixels::Sums(film));
    }
    let (b, n) = body(bytes, b"PFSM", "tile samples", 12)?;
    let expected = region.pixels() * spec.unit_spp() as usize;
    if n != expected {
        return Err(CodecError::Length {
            what: "tile samples (sample count)",
            got: n,
            expected,
        });
    }
    let f = |c: &[u8], k: usize| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap());
    let mut values = Vec::with_capacity(n);
    for (i, c) in b.chunks_exact(12).enumerate() {
        let v = glam::Vec3::new(f(c, 0), f(c, 1), f(c, 2));
        if !v.is_finite() {
            return Err(CodecError::NonFinite(i));
        }
        let value = v.abs().max_element();
        if value > MAX_SAMPLE_VALUE {
            return Err(CodecError::OutOfRange { index: i, value });
        }
        values.push(v);
    }
    Ok(TilePixels::Samples(values))
}

/// Whether a pixel's sums are ones that samples could have made: finite, the sums of squares
/// not negative, consistent with each other (Cauchy-Schwarz: (Σw²L)² <= Σw² Σw²L²), and no
/// sample beyond [`MAX_SAMPLE_VALUE`] (the weighted root mean square bounds the largest).
fn check_sums(p: &PixelStats) -> Result<(), &'static str> {
    let all = [p.sum_w, p.sum_w2]
        .into_iter()
        .chain(p.sum_wl)
        .chain(p.sum_w2l)
        .chain(p.sum_w2l2);
    let mut all = all;
    if !all.all(f64::is_finite) {
        return Err("a sum is not finite");
    }
    if p.sum_w < 0.0 || p.sum_w2 < 0.0 || p.sum_w2l2.iter().any(|&x| x < 0.0) {
        return Err("a sum of weights or squares is negative");
    }
    let max = MAX_SAMPLE_VALUE as f64;
    for c in 0..3 {
        let bound = p.sum_w2 * p.sum_w2l2[c];
        if p.sum_w2l[c] * p.sum_w2l[c] > bound * (1.0 + 1e-9) + 1e-300 {
            return Err("the sums are inconsistent (not the sums of any samples)");
        }
        if p.sum_w2 > 0.0 && p.sum_w2l2[c] / p.sum_w2 > max * max {
            return Err("a sample is beyond the largest value a tile may carry");
        }
        if p.sum_w > 0.0 && (p.sum_wl[c] / p.sum_w).abs() > max {
            return Err("the mean is beyond the largest value a tile may carry");
        }
    }
    Ok(())
}

/// A rendered tile's counters (the worker fills in its timings).
pub fn tile_counters(out: &TileOutput) -> v1::TileCounters {
    v1::TileCounters {
        rays: out.rays,
        invalid_samples: out.invalid_samples,
        nonfinite_records: out.nonfinite_records,
        split_paths: out.split_paths,
        extra_light_samples: out.extra_light_samples,
        ..Default::default()
    }
}

fn kind_to_proto(k: PassKind) -> v1::PassKind {
    match k {
        PassKind::Record => v1::PassKind::Record,
        PassKind::Guided => v1::PassKind::Guided,
        PassKind::Probe => v1::PassKind::Probe,
        PassKind::Path => v1::PassKind::Path,
    }
}

/// The proto form of `spec`; the blob digests are the caller's (empty = none).
pub fn spec_to_proto(spec: &PassSpec) -> v1::PassSpec {
    v1::PassSpec {
        unit: spec.unit,
        iteration: spec.iteration,
        kind: kind_to_proto(spec.kind) as i32,
        first_sample: spec.first_sample,
        spp: spec.spp,
        passes: spec.passes,
        guide: spec.guide(),
        record: spec.record(),
        split: spec.split,
        spp_before: spec.spp_before,
        tree_version: spec.tree_version,
        fraction_version: spec.fraction_version,
        ..Default::default()
    }
}

/// The render crate's spec from its proto form.
pub fn spec_from_proto(p: &v1::PassSpec) -> Result<PassSpec, CodecError> {
    let kind = match v1::PassKind::try_from(p.kind) {
        Ok(v1::PassKind::Record) => PassKind::Record,
        Ok(v1::PassKind::Guided) => PassKind::Guided,
        Ok(v1::PassKind::Probe) => PassKind::Probe,
        Ok(v1::PassKind::Path) => PassKind::Path,
        _ => return Err(CodecError::Kind(p.kind)),
    };
    Ok(PassSpec {
        unit: p.unit,
        iteration: p.iteration,
        kind,
        first_sample: p.first_sample,
        spp: p.spp,
        passes: p.passes,
        spp_before: p.spp_before,
        split: p.split,
        tree_version: p.tree_version,
        fraction_version: p.fraction_version,
    })
}

/// A proto rectangle as a region inside a `width x height` image.
pub fn region_from_proto(r: &v1::Rect, width: u32, height: u32) -> Result<Region, CodecError> {
    let region = Region {
        x0: r.x0,
        y0: r.y0,
        x1: r.x1,
        y1: r.y1,
    };
    if region.is_valid_in(width, height) {
        Ok(region)
    } else {
        Err(CodecError::Region(region))
    }
}

pub fn region_to_proto(r: Region) -> v1::Rect {
    v1::Rect {
        x0: r.x0,
        y0: r.y0,
        x1: r.x1,
        y1: r.y1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn payloads_round_trip_bit_for_bit_and_truncation_is_refused() {
        let fr = vec![
            FractionState {
                theta: -0.1,
                m: 1e-300,
                v: f64::MIN_POSITIVE,
                t: 7,
            };
            3
        ];
        assert_eq!(decode_fractions(&encode_fractions(&fr)).unwrap(), fr);
        let est = vec![0.5f32, 1e-6, 3.0];
        assert_eq!(decode_estimate(&encode_estimate(&est)).unwrap(), est);
        let region = Region {
            x0: 1,
            y0: 2,
            x1: 3,
            y1: 3,
        };
        let mut film = Film::new(2, 1);
        film.pixels[1].add(0.3, glam::Vec3::new(1.0, 2.0, 1e-9));
        film.pixels[1].count = 4;
        let enc = encode_pixels(&film);
        assert_eq!(decode_pixels(&enc, region).unwrap(), film);
        assert!(decode_pixels(&enc[..enc.len() - 1], region).is_err());
        let other = Region { x1: 4, ..region };
        assert!(
            decode_pixels(&enc, other).is_err(),
            "pixel count must match"
        );
        let mut bad = enc.clone();
        bad[0] = b'X';
        assert!(matches!(
            decode_pixels(&bad, region),
            Err(CodecError::Header { .. })
        ));
    }

    #[test]
    fn a_leases_estimate_travels_alone_and_lands_where_the_frames_was() {
        let (w, h) = (5u32, 4u32);
        let frame: Vec<f32> = (0..w * h).map(|i| i as f32 * 0.25).collect();
        let region = Region {
            x0: 1,
            y0: 1,
            x1: 4,
            y1: 3,
        };
        let e = encode_tile_estimate(&frame, w, region).unwrap();
        assert_eq!(e.values.len(), 6 * 4);
        let tile = Region { x1: 3, ..region };
        let back = decode_tile_estimate(&e, (w, h), tile).unwrap();
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let inside = region.x0 <= x && x < region.x1 && region.y0 <= y && y < region.y1;
                let want = if inside { frame[i] } else { 0.0 };
                assert_eq!(back[i].to_bits(), want.to_bits(), "pixel ({x}, {y})");
            }
        }
        assert!(encode_tile_estimate(&[], w, region).is_none());
        let huge = Region {
            x0: 0,
            y0: 0,
            x1: 1024,
            y1: 257,
        };
        assert!(encode_tile_estimate(&vec![1.0; 1024 * 257], 1024, huge).is_none());
        // refused: a short payload, a region outside the frame or not containing the tile,
        // a bad value
        let mut short = e.clone();
        short.values.truncate(20);
        let r = decode_tile_estimate(&short, (w, h), tile);
        assert!(matches!(r, Err(CodecError::Length { .. })), "{r:?}");
        let outside = v1::PixelEstimate {
            region: Some(region_to_proto(Region { x1: 6, ..region })),
            values: vec![0u8; 8 * 4],
        };
        assert!(decode_tile_estimate(&outside, (w, h), tile).is_err());
        let wider = Region { x0: 0, ..region };
        let r = decode_tile_estimate(&e, (w, h), wider);
        assert!(r.is_err(), "the tile must lie inside: {r:?}");
        for bad in [f32::NAN, f32::INFINITY, -1.0] {
            let mut b = e.clone();
            b.values[8..12].copy_from_slice(&bad.to_le_bytes());
            let r = decode_tile_estimate(&b, (w, h), tile);
            assert!(
                matches!(r, Err(CodecError::BadEstimate { index: 2, .. })),
                "{r:?}"
            );
        }
    }

    #[test]
    fn tile_pixels_travel_in_their_units_form() {
        let region = Region {
            x0: 0,
            y0: 0,
            x1: 2,
            y1: 1,
        };
        let spec = |spp, passes| PassSpec {
            unit: 1,
            iteration: 1,
            kind: PassKind::Record,
            first_sample: 0,
            spp,
            passes,
            spp_before: 0,
            split: false,
            tree_version: 1,
            fraction_version: 0,
        };
        // 2 pixels x 3 spp: samples, bit for bit
        let few = spec(1, 3);
        let values: Vec<_> = (0..6)
            .map(|i| glam::Vec3::new(i as f32, 1e-30, 7e19))
            .collect();
        let enc = encode_tile_pixels(&TilePixels::Samples(values.clone()));
        assert_eq!(enc.len(), 9 + 6 * 12, "12 bytes a sample");
        let got = decode_tile_pixels(&enc, &few, region).unwrap();
        assert_eq!(got, TilePixels::Samples(values.clone()));
        assert!(got.fits(&few, region));
        // the wrong count, the wrong form, a non-finite sample: refused
        assert!(decode_tile_pixels(&enc, &spec(1, 2), region).is_err());
        assert!(decode_tile_pixels(&enc, &spec(8, 1), region).is_err());
        let sums = encode_tile_pixels(&TilePixels::Sums(Film::new(2, 1)));
        assert!(decode_tile_pixels(&sums, &few, region).is_err());
        assert!(decode_tile_pixels(&sums, &spec(8, 1), region).is_ok());
        let mut nan = values;
        nan[4].y = f32::NAN;
        let enc = encode_tile_pixels(&TilePixels::Samples(nan.clone()));
        assert_eq!(
            decode_tile_pixels(&enc, &few, region),
            Err(CodecError::NonFinite(4))
        );
        let mut huge = nan;
        huge[4].y = 1.0;
        huge[2].x = 1e30;
        let enc = encode_tile_pixels(&TilePixels::Samples(huge));
        let e = decode_tile_pixels(&enc, &few, region);
        assert!(
            matches!(e, Err(CodecError::OutOfRange { index: 2, .. })),
            "{e:?}"
        );
    }

    #[test]
    fn pixel_sums_are_refused_unless_samples_could_have_made_them() {
        let region = Region {
            x0: 0,
            y0: 0,
            x1: 2,
            y1: 1,
        };
        let spec = PassSpec {
            unit: 1,
            iteration: 1,
            kind: PassKind::Guided,
            first_sample: 0,
            spp: 8,
            passes: 1,
            spp_before: 0,
            split: false,
            tree_version: 1,
            fraction_version: 0,
        };
        let mut film = Film::new(2, 1);
        for k in 0..8 {
            film.pixels[0].add(1.0, glam::Vec3::new(k as f32, 0.5, 1e3));
            film.pixels[1].add(0.5, glam::Vec3::splat(2.0));
        }
        let good = encode_tile_pixels(&TilePixels::Sums(film.clone()));
        assert_eq!(good.len() as u64, tile_pixels_bytes(&spec, region));
        assert!(decode_tile_pixels(&good, &spec, region).is_ok());
        let spoil = |f: &dyn Fn(&mut PixelStats)| {
            let mut bad = film.clone();
            f(&mut bad.pixels[1]);
            decode_tile_pixels(&encode_tile_pixels(&TilePixels::Sums(bad)), &spec, region)
        };
        let bad = |r: Result<TilePixels, CodecError>| {
            matches!(r, Err(CodecError::BadSums { index: 1, .. }))
        };
        assert!(bad(spoil(&|p| p.sum_wl[0] = f64::NAN)));
        assert!(bad(spoil(&|p| p.sum_w2l2[1] = -1.0)));
        // finite, but no samples sum to this
        assert!(bad(spoil(&|p| p.sum_w2l[2] = 1e9)));
        // a sample of 1e30, consistently summed
        assert!(bad(spoil(&|p| {
            *p = PixelStats::default();
            p.add(1.0, glam::Vec3::new(1e30, 0.0, 0.0));
        })));
    }

    #[test]
    fn pass_spec_round_trips_through_proto() {
        let spec = PassSpec {
            unit: 9,
            iteration: 3,
            kind: PassKind::Probe,
            first_sample: (1 << 40) + 5,
            spp: 4,
            passes: 2,
            spp_before: 17,
            split: true,
            tree_version: 3,
            fraction_version: 11,
        };
        assert_eq!(spec_from_proto(&spec_to_proto(&spec)).unwrap(), spec);
        let mut p = spec_to_proto(&spec);
        p.kind = 99;
        assert_eq!(spec_from_proto(&p), Err(CodecError::Kind(99)));
    }
}
