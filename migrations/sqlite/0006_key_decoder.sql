-- The decoder a watermarked asset's bits were written for (src/decoder/registry.rs): the
-- SHA-256 of its decoder weights and sidecar (decoder::artifact::digest_of, hex). A dispute reads
-- the bits with that decoder — the shipped one, the one in the configured weights folder, or one
-- kept in its archive/ folder — and says so when the server holds none with that digest, instead
-- of reading them with another decoder and reporting a false "not detected". Sealed like the
-- reference (XChaCha20-Poly1305 under the master key, AAD "<asset id>/decoder", plaintext = the
-- hex digest) so that it cannot be changed unnoticed. NULL: a key registered before this column;
-- its bits are read with the server's current decoder for their length, as before.
ALTER TABLE keys ADD COLUMN decoder_nonce BLOB;
ALTER TABLE keys ADD COLUMN decoder_ct BLOB;
