"""Golden telegrams written by hand from the published format, not by our encoder.

The scan: serial 0x89A27F, counters 1234/1238, 50 Hz, 36 kHz, DIST1 with scale factor 2.0
(``40000000``) and RSSI1, start -45° (``FFF92230``), step 0.5° (``1388``), five points; a device
name with a space in it (``B LMS111 left``: length 11, as a real LMS sends ``B not defined``)
and a time block 2024-05-31 23:59:58.999999.
"""

from __future__ import annotations

SCAN_COLA_A = (
    b"\x02sSN LMDscandata 1 1 89A27F 0 0 4D2 4D6 A1B2C3D4 A1B2D000 0 0 0 0 0 1388 168 0 "
    b"2 DIST1 40000000 00000000 FFF92230 1388 5 0 1F4 3E8 FFFF 7D0 "
    b"RSSI1 3F800000 00000000 FFF92230 1388 5 0 C8 FE 0 64 "
    b"0 0 1 B LMS111 left 0 1 7E8 5 1F 17 3B 3A F423F 0\x03"
)

_SCAN_COLA_B_PAYLOAD = bytes.fromhex(
    "73534e204c4d447363616e6461746120"  # "sSN LMDscandata "
    "0001"  # version
    "0001"  # device number
    "0089a27f"  # serial number
    "0000"  # device status: 2 x uint8
    "04d2"  # telegram counter 1234
    "04d6"  # scan counter 1238
    "a1b2c3d4"  # time since start-up, µs
    "a1b2d000"  # time of transmission, µs
    "0000"  # digital inputs
    "0000"  # digital outputs
    "0000"  # reserved
    "00001388"  # scan frequency 50.00 Hz
    "00000168"  # measurement frequency 360 x 100 Hz
    "0000"  # no encoders
    "0002"  # two 16-bit channels
    "4449535431"  # DIST1
    "40000000"  # scale 2.0
    "00000000"  # offset 0.0
    "fff92230"  # start -45.0000°
    "1388"  # step 0.5000°
    "0005"  # five values
    "0000"
    "01f4"
    "03e8"
    "ffff"
    "07d0"
    "5253534931"  # RSSI1
    "3f800000"  # scale 1.0
    "00000000"
    "fff92230"
    "1388"
    "0005"
    "0000"
    "00c8"
    "00fe"
    "0000"
    "0064"
    "0000"  # no 8-bit channels
    "0000"  # no position
    "0001"
    "000b"
    "4c4d53313131206c656674"  # name: uint16 length 11, "LMS111 left"
    "0000"  # no comment
    "0001"
    "07e8"
    "05"
    "1f"
    "17"
    "3b"
    "3a"
    "000f423f"  # time block
    "0000"  # no event info
)
SCAN_COLA_B = b"\x02\x02\x02\x02" + b"\x00\x00\x00\x9a" + _SCAN_COLA_B_PAYLOAD + b"\xf4"
SCAN_COLA_B_PAYLOAD = _SCAN_COLA_B_PAYLOAD

# From the telegram listing / SICK's own test vectors.
SEN_LMDSCANDATA_1_COLA_B = bytes.fromhex(
    "02020202 00000011 73454e204c4d447363616e64617461 20 01 33".replace(" ", "")
)
SRN_LMDSCANDATA_COLA_B = bytes.fromhex(
    "02020202 0000000f 73524e204c4d447363616e64617461 05".replace(" ", "")
)
SET_ACCESS_MODE_COLA_B = bytes.fromhex(
    "02020202 00000017 734d4e20 5365744163636573734d6f6465 20 03f4724744 b3".replace(" ", "")
)
SAN_SET_ACCESS_MODE_1_COLA_B = bytes.fromhex(
    "02020202 00000013 73414e20 5365744163636573734d6f6465 20 01 38".replace(" ", "")
)
SMN_RUN_COLA_B = bytes.fromhex("02020202 00000007 734d4e20 52756e 19".replace(" ", ""))
SAN_RUN_1_COLA_B = bytes.fromhex("02020202 00000009 73414e20 52756e 20 01 34".replace(" ", ""))
SWN_EIHSTCOLA_0_COLA_B = bytes.fromhex(
    "02020202 0000000f 73574e20 45494873744 36f6c61 20 00 08".replace(" ", "")
)
SWA_EIHSTCOLA_COLA_B = bytes.fromhex(
    "02020202 0000000d 73574120 45494873744 36f6c61 27".replace(" ", "")
)
SFA_0A_COLA_B = b"\x02\x02\x02\x02\x00\x00\x00\x05sFA\x00\n~"  # a real LMS answer
