//! The trained watermark model as files: decoder weights, encoder weights and a JSON sidecar,
//! and the weights shipped inside the binary.
//!
//! # Files
//!
//! For an artifact path `P` (e.g. `weights/decoder-32.bpk`):
//!
//! - `P`: the decoder's weights (burnpack, BatchNorm running statistics included);
//! - `P` with extension `.encoder.bpk` (`weights/decoder-32.encoder.bpk`): the encoder's weights,
//!   needed only by `decoder eval` (the decoder alone decodes);
//! - `P` with extension `.json` (`weights/decoder-32.json`): the [`Sidecar`]: message length,
//!   both architectures, embedding strength, the optional [`Whitening`] of the logits, the
//!   training configuration and the training record (steps, wall time, final held-out metrics).
//!
//! All three are written atomically (temporary file + rename), the sidecar last.
//!
//! # Shipped weights
//!
//! `weights/decoder-{32,48,64}.{bpk,encoder.bpk,json}` are compiled into the binary with
//! `include_bytes!` (burn loads burnpack records from memory), so `splatmark` needs no files next
//! to it. Until a model is trained and committed, its three files are **empty placeholders**, and
//! [`WatermarkModel::shipped`] answers [`WeightsError::NotShipped`]; other message lengths get
//! [`WeightsError::NoShippedWeights`].

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::store::{ModuleRecord, RecordError};
use burn::tensor::{Bytes, Device, Tensor, TensorData};

use super::encoder::Encoder;
use super::model::HiddenDecoder;
use super::projection::ViewProjection;

mod sidecar;
pub use sidecar::{DecoderArch, EncoderArch, Sidecar, TrainingRecord, WhiteningReport};

/// Sidecar format tag.
pub const FORMAT: &str = "splatmark-decoder/1";

/// Message lengths with shipped weights.
pub const SHIPPED_BITS: [usize; 3] = [32, 48, 64];

/// Why a model could not be loaded, saved or used.
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    /// The shipped weights for this length are still placeholders.
    #[error(
        "no trained weights are shipped for {bits} bits yet (weights/decoder-{bits}.* are placeholders); \
         train them with `splatmark decoder train` or pass --weights FILE"
    )]
    NotShipped { bits: usize },
    /// No shipped weights exist for this length at all.
    #[error("splatmark ships weights for 32, 48 and 64 bits only, not {bits}; pass --weights FILE")]
    NoShippedWeights { bits: usize },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A sidecar is not valid JSON of the expected shape.
    #[error("{path}: invalid sidecar: {source}")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    /// Weights do not load (corrupt, or another architecture).
    #[error("{path}: {message}")]
    Record { path: PathBuf, message: String },
    /// The sidecar and the request disagree.
    #[error("{0}")]
    Mismatch(String),
    /// Evaluation needs the encoder, and the artifact has none.
    #[error("{0}: no encoder weights next to the decoder (needed to embed messages)")]
    NoEncoder(PathBuf),
    /// An image could not be read.
    #[error("cannot read image {path}: {source}")]
    Image {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    /// An attack failed.
    #[error("attack {name}: {message}")]
    Attack { name: String, message: String },
}

/// The encoder's residual for images `[B, 3, H, W]` in [0, 1] and messages `[B, L]`, computed at
/// 1/2^`levels` resolution: the encoder sees the block means of 2^levels × 2^levels blocks (the
/// Haar LL band, scaled back to image range) and its residual is resized back to H × W
/// (bilinear), so it is smooth rather than blocky. The decoder reads only that LL band anyway;
/// running the encoder at that resolution makes it 4^levels times cheaper. `levels = 0` is the
/// plain full-resolution [`Encoder::residual`].
pub fn encoder_residual(
    encoder: &Encoder,
    image: Tensor<4>,
    message: Tensor<2>,
    levels: usize,
) -> Tensor<4> {
    if levels == 0 {
        return encoder.residual(image, message);
    }
    let [_, _, h, w] = image.dims();
    let f = 1usize << levels;
    let small = super::dwt::ll_band(image, levels).div_scalar(f as f64);
    let r = encoder.residual(small, message);
    let [_, _, sh, sw] = r.dims();
    // Bilinear, half-pixel centres, as gathers (back-propagates on the GPU too).
    let up = crate::attack::diff::resize(r, [sh * f, sw * f]);
    if (sh * f, sw * f) == (h, w) {
        up
    } else {
        up.narrow(2, 0, h).narrow(3, 0, w)
    }
}

/// The sidecar path of an artifact: `P` with extension `.json`.
pub fn sidecar_path(out: &Path) -> PathBuf {
    out.with_extension("json")
}

/// The coarse decoder beside the artifact at `P` (`decoder-32.bpk` → `decoder-32.coarse.bpk`):
/// the one an embedding writes for when the asset leaves the fidelity budget free
/// (`embed::pipeline`, `EmbedOptions::coarse_margin_db`; `decoder::registry`).
pub fn coarse_path(main: &Path) -> PathBuf {
    main.with_extension("coarse.bpk")
}

/// The encoder path of an artifact: `P` with extension `.encoder.bpk`.
pub fn encoder_path(out: &Path) -> PathBuf {
    out.with_extension("encoder.bpk")
}

/// A module's weights as burnpack bytes.
pub fn to_burnpack<M: Module>(module: M) -> Result<Vec<u8>, RecordError> {
    Ok(module.into_record().into_bytes()?.to_vec())
}

/// `module` with weights from burnpack bytes (parameter ids restored from the record).
pub fn from_burnpack<M: Module>(module: M, bytes: Vec<u8>) -> Result<M, RecordError> {
    module.try_load_record(ModuleRecord::from_bytes(Bytes::from_bytes_vec(bytes))?)
}

/// Writes `bytes` to `path` atomically: a temporary file in the same folder, fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), WeightsError> {
    use std::io::Write;
    let io = |source| WeightsError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io)?;
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
    tmp.write_all(bytes).map_err(io)?;
    tmp.as_file().sync_all().map_err(io)?;
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}

macro_rules! shipped {
    ($bits:literal) => {
        (
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/weights/decoder-",
                $bits,
                ".bpk"
            ))
            .as_slice(),
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/weights/decoder-",
                $bits,
                ".encoder.bpk"
            ))
            .as_slice(),
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/weights/decoder-",
                $bits,
                ".json"
            ))
            .as_slice(),
        )
    };
}

/// The shipped `(decoder, encoder, sidecar)` bytes for `bits` (empty slices = placeholders).
pub fn shipped_bytes(bits: usize) -> Option<(&'static [u8], &'static [u8], &'static [u8])> {
    match bits {
        32 => Some(shipped!("32")),
        48 => Some(shipped!("48")),
        64 => Some(shipped!("64")),
        _ => None,
    }
}

/// The shipped coarse decoder's `(decoder, sidecar)` bytes for `bits`
/// (`weights/decoder-{bits}.coarse.*`: the colour-Fourier decoder at colour scale 12, for
/// assets that leave the fidelity budget free). Shipped for 32 bits only: the only length it
/// was measured at (docs/RESULTS.md).
pub fn shipped_coarse_bytes(bits: usize) -> Option<(&'static [u8], &'static [u8])> {
    match bits {
        32 => Some((
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/weights/decoder-32.coarse.bpk"
            ))
            .as_slice(),
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/weights/decoder-32.coarse.json"
            ))
            .as_slice(),
        )),
        _ => None,
    }
}

/// Whether trained weights are shipped for `bits`.
pub fn is_shipped(bits: usize) -> bool {
    shipped_bytes(bits).is_some_and(|(d, _, s)| !d.is_empty() && !s.is_empty())
}

/// A trained model ready for inference: frozen decoder (and encoder), sidecar, device.
#[derive(Debug, Clone)]
pub struct WatermarkModel {
    pub sidecar: Sidecar,
    pub decoder: HiddenDecoder,
    pub encoder: Option<Encoder>,
    /// The asset reference ([`with_reference`](Self::with_reference)): the unmarked asset's
    /// own mean logits, subtracted from every (whitened) logit vector. `None` for the plain
    /// decoder.
    pub reference: Option<Vec<f32>>,
    /// The per-asset view projection ([`with_projection`](Self::with_projection)), applied to
    /// the pooled features before the head. `None` for the plain decoder.
    pub projection: Option<ViewProjection>,
    /// [`digest_of`] the files the model was loaded from; `None` for a model made in memory
    /// ([`digest`](Self::digest) then hashes what [`save`](Self::save) would write).
    pub file_digest: Option<String>,
}

/// The identity of a decoder artifact: SHA-256 (hex) of its decoder weights and its sidecar,
/// each length-prefixed — the two files that decide what an image decodes to (the encoder does
/// not). A watermark's key records it, so that a dispute reads the bits with the decoder that
/// wrote them (`decoder::registry`).
pub fn digest_of(decoder: &[u8], sidecar: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(b"splatmark-decoder-digest/1\0");
    for part in [decoder, sidecar] {
        h.update((part.len() as u64).to_le_bytes());
        h.update(part);
    }
    hex::encode(h.finalize())
}

/// The first 12 hex digits of a digest, for messages.
pub fn short_digest(digest: &str) -> &str {
    digest.get(..12).unwrap_or(digest)
}

impl WatermarkModel {
    /// Message length.
    pub fn bits(&self) -> usize {
        self.sidecar.bits
    }

    /// The decoder's identity ([`digest_of`]): of the files it was loaded from, or for a model
    /// made in memory of the bytes [`save`](Self::save) would write.
    pub fn digest(&self) -> String {
        match &self.file_digest {
            Some(d) => d.clone(),
            None => {
                let dec = to_burnpack(self.decoder.clone()).expect("weights serialise");
                let json = serde_json::to_vec_pretty(&self.sidecar).expect("sidecar serialises");
                digest_of(&dec, &json)
            }
        }
    }

    /// The device the decoder's weights live on (without its autodiff setting): tensors fed to
    /// the model are made there.
    pub fn device(&self) -> Device {
        use burn::module::Module;
        self.decoder
            .devices()
            .into_iter()
            .next()
            .unwrap_or_else(Device::flex)
    }

    /// The same model with its networks on `device` (e.g. a GPU worker's burn device); the
    /// sidecar, reference and projection are host data and stay as they are.
    pub fn to_device(self, device: &Device) -> Self {
        use burn::module::Module;
        Self {
            decoder: self.decoder.to_device(device),
            encoder: self.encoder.map(|e| e.to_device(device)),
            ..self
        }
    }

    /// Builds the model from the bytes of its three files; `origin` names them in errors.
    pub fn from_bytes(
        decoder: &[u8],
        encoder: Option<&[u8]>,
        sidecar: &[u8],
        origin: &Path,
        device: &Device,
    ) -> Result<Self, WeightsError> {
        let file_digest = Some(digest_of(decoder, sidecar));
        let sidecar: Sidecar =
            serde_json::from_slice(sidecar).map_err(|source| WeightsError::Json {
                path: sidecar_path(origin),
                source,
            })?;
        sidecar.check(origin)?;
        let record = |path: PathBuf| {
            move |e: RecordError| WeightsError::Record {
                path,
                message: e.to_string(),
            }
        };
        let dec = from_burnpack(sidecar.decoder_config().init(device), decoder.to_vec())
            .map_err(record(origin.to_path_buf()))?
            .frozen();
        let enc = match (sidecar.encoder_config(), encoder) {
            (Some(cfg), Some(bytes)) if !bytes.is_empty() => Some(
                from_burnpack(cfg.init_encoder(device), bytes.to_vec())
                    .map_err(record(encoder_path(origin)))?
                    .freeze(),
            ),
            _ => None,
        };
        Ok(Self {
            sidecar,
            decoder: dec,
            encoder: enc,
            reference: None,
            projection: None,
            file_digest,
        })
    }

    /// Loads the artifact at `path` (decoder weights; the sidecar and, if present, the encoder
    /// next to it).
    pub fn load(path: &Path, device: &Device) -> Result<Self, WeightsError> {
        let read = |p: &Path| {
            std::fs::read(p).map_err(|source| WeightsError::Io {
                path: p.to_path_buf(),
                source,
            })
        };
        let decoder = read(path)?;
        let sidecar = read(&sidecar_path(path))?;
        let enc_path = encoder_path(path);
        let encoder = if enc_path.is_file() {
            Some(read(&enc_path)?)
        } else {
            None
        };
        Self::from_bytes(&decoder, encoder.as_deref(), &sidecar, path, device)
    }

    /// The weights shipped in the binary for `bits`.
    pub fn shipped(bits: usize, device: &Device) -> Result<Self, WeightsError> {
        let (decoder, encoder, sidecar) =
            shipped_bytes(bits).ok_or(WeightsError::NoShippedWeights { bits })?;
        if decoder.is_empty() || sidecar.is_empty() {
            return Err(WeightsError::NotShipped { bits });
        }
        let origin = PathBuf::from(format!("<shipped>/weights/decoder-{bits}.bpk"));
        let model = Self::from_bytes(decoder, Some(encoder), sidecar, &origin, device)?;
        if model.bits() != bits {
            return Err(WeightsError::Mismatch(format!(
                "shipped weights for {bits} bits decode {} bits",
                model.bits()
            )));
        }
        Ok(model)
    }

    /// The coarse decoder shipped in the binary for `bits` ([`shipped_coarse_bytes`]), `None`
    /// when none is shipped for that length.
    pub fn shipped_coarse(bits: usize, device: &Device) -> Result<Option<Self>, WeightsError> {
        let Some((decoder, sidecar)) = shipped_coarse_bytes(bits) else {
            return Ok(None);
        };
        let origin = PathBuf::from(format!("<shipped>/weights/decoder-{bits}.coarse.bpk"));
        let model = Self::from_bytes(decoder, None, sidecar, &origin, device)?;
        if model.bits() != bits {
            return Err(WeightsError::Mismatch(format!(
                "the shipped coarse weights for {bits} bits decode {} bits",
                model.bits()
            )));
        }
        Ok(Some(model))
    }

    /// `--weights FILE` if given, else the shipped weights; checks the message length.
    pub fn resolve(
        weights: Option<&Path>,
        bits: usize,
        device: &Device,
    ) -> Result<Self, WeightsError> {
        let model = match weights {
            Some(p) => Self::load(p, device)?,
            None => Self::shipped(bits, device)?,
        };
        if model.bits() != bits {
            return Err(WeightsError::Mismatch(format!(
                "the weights decode {} bits, --bits asks for {bits}",
                model.bits()
            )));
        }
        Ok(model)
    }

    /// Writes the artifact to `out` (decoder, encoder if any, sidecar last), atomically.
    pub fn save(&self, out: &Path) -> Result<(), WeightsError> {
        let record = |path: &Path| {
            let path = path.to_path_buf();
            move |e: RecordError| WeightsError::Record {
                path,
                message: e.to_string(),
            }
        };
        let dec = to_burnpack(self.decoder.clone()).map_err(record(out))?;
        write_atomic(out, &dec)?;
        if let Some(enc) = &self.encoder {
            let p = encoder_path(out);
            let bytes = to_burnpack(enc.clone()).map_err(record(&p))?;
            write_atomic(&p, &bytes)?;
        }
        let json = serde_json::to_vec_pretty(&self.sidecar).expect("sidecar serialises");
        write_atomic(&sidecar_path(out), &json)
    }

    /// Decoder logits `[B, L]` of images `[B, 3, H, W]` in [0, 1], whitened when the sidecar
    /// has a whitening, as one vector per image.
    pub fn logits(&self, images: Tensor<4>) -> Vec<Vec<f32>> {
        let flat = self
            .forward(images)
            .try_into_vec_as::<f32>()
            .expect("logits readable");
        flat.chunks_exact(self.bits())
            .map(<[f32]>::to_vec)
            .collect()
    }

    /// Decoder logits `[B, L]` as a tensor (whitened when the sidecar has a whitening); on an
    /// autodiff device gradients flow back to `images`.
    pub fn forward(&self, images: Tensor<4>) -> Tensor<2> {
        self.forward_pooled(self.decoder.pooled(images))
    }

    /// [`forward`](Self::forward) from the decoder's pooled features `[B, F]`
    /// ([`features`](Self::features)): through the projection or matched head, the whitening
    /// and the reference.
    pub fn forward_pooled(&self, pooled: Tensor<2>) -> Tensor<2> {
        let z = match &self.projection {
            // The matched head replaces the decoder's head and its whitening.
            Some(p) if p.head.is_some() => p.matched_logits(pooled),
            Some(p) => self.whiten(self.decoder.head(p.apply(pooled))),
            None => self.whiten(self.decoder.head(pooled)),
        };
        match &self.reference {
            Some(r) => {
                let device = z.device();
                let r = Tensor::<2>::from_data(TensorData::new(r.clone(), [1, r.len()]), &device);
                z.sub(r)
            }
            None => z,
        }
    }

    fn whiten(&self, z: Tensor<2>) -> Tensor<2> {
        match &self.sidecar.whitening {
            Some(w) => w.apply(z),
            None => z,
        }
    }

    /// The model decoding relative to an asset: `reference` (the unmarked asset's mean
    /// logits over its views, [`crate::embed::pipeline::reference_logits`]) is subtracted from
    /// every logit vector, so the unmarked asset itself decodes to logits near 0 — no bit
    /// starts stuck at the value the asset's colours happen to give it, and the message only
    /// has to move each bit past the asset's own view-to-view spread (informed detection: the
    /// owner has the original).
    ///
    /// # Panics
    /// If `reference` does not have one value per bit.
    pub fn with_reference(mut self, reference: Vec<f32>) -> Self {
        assert_eq!(reference.len(), self.bits(), "one reference value per bit");
        self.reference = Some(reference);
        self
    }

    /// The model decoding through an asset's view projection ([`ViewProjection`]), or its
    /// matched head when the projection carries one.
    ///
    /// # Panics
    /// If the projection does not have one value per pooled feature, or its matched head
    /// another number of bits.
    pub fn with_projection(mut self, projection: ViewProjection) -> Self {
        assert_eq!(
            projection.features(),
            self.decoder.feature_count(),
            "one projection mean per pooled feature"
        );
        assert!(
            projection.head.is_none() || projection.head_bits() == self.bits(),
            "a matched head for {} bits, the model reads {}",
            projection.head_bits(),
            self.bits()
        );
        self.projection = Some(projection);
        self
    }

    /// The decoder's pooled features (before any projection), one vector per image.
    pub fn features(&self, images: Tensor<4>) -> Vec<Vec<f32>> {
        let f = self.decoder.feature_count();
        let flat = self
            .decoder
            .pooled(images)
            .try_into_vec_as::<f32>()
            .expect("features readable");
        flat.chunks_exact(f).map(<[f32]>::to_vec).collect()
    }

    /// Raw (never whitened) logits, one vector per image.
    pub fn raw_logits(&self, images: Tensor<4>) -> Vec<Vec<f32>> {
        let flat = self
            .decoder
            .forward(images)
            .try_into_vec_as::<f32>()
            .expect("logits readable");
        flat.chunks_exact(self.bits())
            .map(<[f32]>::to_vec)
            .collect()
    }

    /// Watermarked images `clamp(x + strength · E(x, m), 0, 1)` for images `[B, 3, H, W]` and
    /// messages (one `Vec<bool>` of L bits per image).
    ///
    /// # Panics
    /// Without an encoder, or if the shapes do not fit.
    pub fn embed(&self, images: Tensor<4>, messages: &[Vec<bool>]) -> Tensor<4> {
        let encoder = self.encoder.as_ref().expect("model has an encoder");
        let levels = self.sidecar.encoder.as_ref().map_or(0, |e| e.levels);
        let l = self.bits();
        let bits: Vec<f32> = messages
            .iter()
            .flat_map(|m| m.iter().map(|&b| f32::from(u8::from(b))))
            .collect();
        let device = images.device();
        let m = Tensor::<2>::from_data(TensorData::new(bits, [messages.len(), l]), &device);
        let residual = encoder_residual(encoder, images.clone(), m, levels);
        images
            .add(residual.mul_scalar(self.sidecar.strength))
            .clamp(0.0, 1.0)
    }
}

/// An 8-bit RGB image as a `[1, 3, H, W]` tensor in [0, 1].
pub fn rgb8_tensor(img: &image::RgbImage, device: &Device) -> Tensor<4> {
    rgb8_batch(std::slice::from_ref(img), device)
}

/// Same-size 8-bit RGB images as a `[B, 3, H, W]` tensor in [0, 1].
///
/// # Panics
/// If the sizes differ or `images` is empty.
pub fn rgb8_batch(images: &[image::RgbImage], device: &Device) -> Tensor<4> {
    let (w, h) = images[0].dimensions();
    let (w, h) = (w as usize, h as usize);
    let mut data = vec![0.0f32; images.len() * 3 * w * h];
    for (k, img) in images.iter().enumerate() {
        assert_eq!(img.dimensions(), (w as u32, h as u32), "same-size images");
        let base = k * 3 * w * h;
        for (i, p) in img.pixels().enumerate() {
            for c in 0..3 {
                data[base + c * w * h + i] = f32::from(p.0[c]) / 255.0;
            }
        }
    }
    Tensor::from_data(TensorData::new(data, [images.len(), 3, h, w]), device)
}

/// A `[B, 3, H, W]` tensor in [0, 1] as 8-bit RGB images (rounded).
pub fn tensor_to_rgb8(t: Tensor<4>) -> Vec<image::RgbImage> {
    let [b, _, h, w] = t.dims();
    let data = t.try_into_vec_as::<f32>().expect("image readable");
    (0..b)
        .map(|k| {
            let base = k * 3 * h * w;
            image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
                let i = y as usize * w + x as usize;
                image::Rgb(std::array::from_fn(|c| {
                    (data[base + c * h * w + i] * 255.0)
                        .round()
                        .clamp(0.0, 255.0) as u8
                }))
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_shipped_length_loads_and_others_are_typed_errors() {
        let d = Device::flex();
        for bits in SHIPPED_BITS {
            let m = WatermarkModel::shipped(bits, &d).unwrap_or_else(|e| panic!("{bits}: {e}"));
            assert_eq!(m.bits(), bits);
            assert!(is_shipped(bits));
            // The shipped decoders are the seeded colour-Fourier ones (docs/DECODER.md): no
            // encoder, a whitening fitted on images, and the command that made them.
            assert_eq!(m.sidecar.decoder.fourier, 128, "{bits}");
            assert!(m.encoder.is_none(), "{bits}");
            assert_eq!(
                m.sidecar.whitening.as_ref().expect("whitening").mean.len(),
                bits
            );
            let record = m.sidecar.record.as_ref().expect("record");
            let command = record.command.as_deref().expect("command");
            assert!(command.contains("--fourier 128"), "{command}");
        }
        assert!(matches!(
            WatermarkModel::shipped(40, &d),
            Err(WeightsError::NoShippedWeights { bits: 40 })
        ));
    }

    #[test]
    fn paths_next_to_the_decoder() {
        let p = Path::new("weights/decoder-32.bpk");
        assert_eq!(sidecar_path(p), Path::new("weights/decoder-32.json"));
        assert_eq!(encoder_path(p), Path::new("weights/decoder-32.encoder.bpk"));
    }
}
