//! Deterministic synthetic scenes for tests and benchmarks.
//!
//! [`object_scene`] builds something shaped like a real 3D-GS capture of an object: flat,
//! surfel-like Gaussians scattered over a bumpy unit sphere, sized so that the surface is covered
//! about twice over whatever their number (so screen footprints shrink as the count grows, as in
//! real scenes), with a long tail of larger Gaussians and a spread of opacities.

use crate::scene::Gaussians;

/// SplitMix64: a tiny, well-distributed generator with a fixed stream per seed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    /// The generator's whole state: `Rng::new(r.state())` continues `r`'s stream exactly.
    pub fn state(&self) -> u64 {
        self.0
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * self.uniform()
    }
    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.uniform().max(1e-7);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

/// `n` Gaussians on a bumpy unit sphere around the origin (see the module docs).
pub fn object_scene(n: usize, sh_degree: u8, seed: u64) -> Gaussians {
    let mut rng = Rng::new(seed);
    let mut g = Gaussians::with_capacity(n, sh_degree);
    let base_sigma = (2.0 / n.max(1) as f32).sqrt();
    let rest = Gaussians::rest_len_for(sh_degree);
    for _ in 0..n {
        let d = loop {
            let v = [rng.normal(), rng.normal(), rng.normal()];
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if l > 1e-3 {
                break v.map(|x| x / l);
            }
        };
        let bump = 1.0 + 0.08 * (5.0 * d[0]).sin() * (4.0 * d[1]).cos() + 0.01 * rng.normal();
        g.means.push(d.map(|x| x * bump));
        // Log-normal size around the coverage size; flat along one axis.
        let s = base_sigma * (0.6 * rng.normal()).exp();
        g.log_scales
            .push([s.ln(), (s * rng.range(0.5, 1.0)).ln(), (s * 0.1).ln()]);
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let l = q.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        g.rotations.push(q.map(|x| x / l));
        g.opacity_logits.push(1.0 + 1.5 * rng.normal());
        let hue = [d[0] * 1.2, d[1] * 1.2, d[2] * 1.2];
        g.sh_dc.push(hue.map(|h| h + 0.2 * rng.normal()));
        for _ in 0..rest {
            g.sh_rest.push(0.1 * rng.normal());
        }
    }
    g
}
