-- The matched head of a watermarked asset (docs/DECODER.md, "matched head"; eq. `matchedhead` in
-- src/decoder/projection.rs): the L directions in the decoder's pooled-feature space the job
-- wrote the bits along, fitted on the unmarked original alone (independent of the payload), that
-- a dispute reads the bits through. Sealed like the reference (XChaCha20-Poly1305 under the
-- master key, AAD "<asset id>/head", plaintext = the projection as JSON) so that it cannot be
-- changed unnoticed. NULL: the job read the bits through the shipped decoder's own head.
ALTER TABLE keys ADD COLUMN head_nonce BLOB;
ALTER TABLE keys ADD COLUMN head_ct BLOB;
