-- A secret random mask per job and per watermarked asset. The service embeds the payload
-- message XOR mask, so that the bits tested in a dispute are uniformly random whatever message
-- the owner chose: for an image that does not carry the watermark, the number of matching bits
-- is then exactly Binomial(n, 1/2) even when the decoder favours some bit values.
-- Sealed like the message (XChaCha20-Poly1305 under the master key, AAD "<message AAD>/mask").
-- NULL in rows written before this migration: their mask is all zeros (payload = message).
ALTER TABLE jobs ADD COLUMN mask_nonce BYTEA;
ALTER TABLE jobs ADD COLUMN mask_ct BYTEA;
ALTER TABLE keys ADD COLUMN mask_nonce BYTEA;
ALTER TABLE keys ADD COLUMN mask_ct BYTEA;
