//! Decoding image files without trusting the decoder: `image`'s JPEG decoder (zune-jpeg) still
//! panics on some malformed files instead of returning an error (an assertion in its upsampler,
//! found by `fuzz/`; the file is in fuzz/regressions/image/). Every reader of image files —
//! dispute images in `/v1/verify`, the CLI's `decode` and `verify`, the decoder's training and
//! evaluation folders — goes through [`open`] or [`guarded`], so such a file is a decoding error
//! like any other.

use std::cell::Cell;
use std::path::Path;

use image::error::{DecodingError, ImageFormatHint};
use image::{DynamicImage, ImageError};

/// What a caught decoder panic is reported as.
pub const DECODER_PANIC: &str = "the image decoder failed on this file (malformed data)";

thread_local! {
    static QUIET_PANICS: Cell<bool> = const { Cell::new(false) };
}

/// `f`, with a panic caught instead of unwinding further — and not reported by the panic hook:
/// the default hook would print it and, with `RUST_BACKTRACE` set, symbolise a backtrace, which
/// costs ~300 MB of resident memory that is never given back (measured by the hostile corpus).
/// Panics elsewhere, on any thread, are reported as before.
pub fn guarded<R>(f: impl FnOnce() -> R) -> std::thread::Result<R> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET_PANICS.with(Cell::get) {
                previous(info);
            }
        }));
    });
    QUIET_PANICS.with(|q| q.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET_PANICS.with(|q| q.set(false));
    r
}

/// The error a caught decoder panic becomes.
pub fn panic_error() -> ImageError {
    ImageError::Decoding(DecodingError::new(ImageFormatHint::Unknown, DECODER_PANIC))
}

/// Decodes the image file at `path` (format from its content, then its extension), a decoder
/// panic reported as [`panic_error`].
pub fn open(path: &Path) -> Result<DynamicImage, ImageError> {
    let reader = image::ImageReader::open(path)?.with_guessed_format()?;
    guarded(|| reader.decode()).unwrap_or_else(|_| {
        tracing::warn!(path = %path.display(), "the image decoder panicked on a malformed file");
        Err(panic_error())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const PANICKING_JPEG: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fuzz/regressions/image/zune_jpeg_progressive_upsample_panic.jpg"
    );

    #[test]
    fn a_file_the_decoder_panics_on_is_a_decoding_error() {
        let err = open(Path::new(PANICKING_JPEG)).unwrap_err();
        assert!(matches!(err, ImageError::Decoding(_)), "{err:?}");
        assert!(err.to_string().contains(DECODER_PANIC), "{err}");
    }

    #[test]
    fn good_files_decode_and_missing_ones_are_io_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        image::RgbImage::from_pixel(7, 5, image::Rgb([1, 2, 3]))
            .save(&p)
            .unwrap();
        let img = open(&p).unwrap().to_rgb8();
        assert_eq!(
            (img.width(), img.height(), img.get_pixel(6, 4).0),
            (7, 5, [1, 2, 3])
        );
        assert!(matches!(
            open(&dir.path().join("missing.png")),
            Err(ImageError::IoError(_))
        ));
    }
}
