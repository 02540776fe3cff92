"""motok.control"""
