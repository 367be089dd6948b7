-- The asset reference of a watermarked asset (docs/DECODER.md, "asset reference"): the original
-- scene's mean decoder logits over the job's training views, which a dispute subtracts before
-- reading the bits. Not secret (it is computed from the unmarked original, independent of the
-- payload), but sealed like the key (XChaCha20-Poly1305 under the master key, AAD
-- "<asset id>/reference", plaintext = the logits as little-endian f32) so that it cannot be
-- changed unnoticed. NULL: the job decoded without a reference.
ALTER TABLE keys ADD COLUMN reference_nonce BLOB;
ALTER TABLE keys ADD COLUMN reference_ct BLOB;
