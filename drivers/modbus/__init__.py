"""Modbus TCP / RTU channels (thermocouple modules such as ADAM-6018/4018 or ioLogik E1262).

Keys follow Home Assistant's modbus integration (hub, device_id, address, input_type, data_type,
swap, scale, offset, nan_value) so a lab describes its own module in the config, without code.
"""
