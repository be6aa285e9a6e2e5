"""Sound bounds over boxes: interval, Taylor-model and linear-relaxation enclosures of the
gain network and of D, and sound eigenvalue bounds. The MPDI box bound is built from
stages (`certify.enclose.stages`) chosen by one options object per proof
(`certify.enclose.options`) and run by `certify.enclose.mpdi.mpdi_box_bounds`; the side
proofs' bounds are in `certify.enclose.side`."""
