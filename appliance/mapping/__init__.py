"""Maps of objects: a worker's 3D map and the vehicle's, their pallets, and their merging
(Kinouchi et al., section 2.2). Pure: arrays and bytes in, maps out; no I/O, no clock."""
