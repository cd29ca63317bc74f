"""The emulated CiA 406 linear position sensor, one canopen ``LocalNode`` per cylinder: the node
(:mod:`.node`), its object dictionary's live objects (:mod:`.objects`), TPDOs (:mod:`.pdo`),
EMCY (:mod:`.emcy`), node and life guarding (:mod:`.guarding`), the SDO server's gate
(:mod:`.sdo_gate`), the parameters a master stores (:mod:`.storage`) and the canopen network
it lives on (:mod:`.network`)."""
