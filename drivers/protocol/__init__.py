"""Device protocol maps shared by the drivers (drivers/) and the emulated devices (sim_backend/emulators/):
the CiA 408 valve object map (valve408), the analog module's Modbus register map (modbus_map) and the
displacement amplifier's serial protocol (dta). Pure Python, no hardware library; documented in
drivers/devicemaps/."""
